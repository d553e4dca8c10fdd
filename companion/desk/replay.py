"""``companion replay DIR``: the mapper over a recording, as fast as possible (docs/replay.md).

Reads any layout :mod:`companion.desk.recordings` knows (the service's own ``--record`` folder, a TUM
folder, EuRoC MAV, a COLMAP text model), runs the same pipeline as the daemon's mapper worker frame by frame
(Harris detector -> :class:`Mapper` with the terrain map as depth prior -> :class:`TerrainGrid`),
and writes to ``--output``:

* ``metrics.json``: frames processed / without navigation / unreadable, mapper rates (frames/s),
  converged points, cells mapped, and ``reference`` (map error) when ``--reference`` is given;
* ``terrain_map.png``: the height map with the camera path; ``terrain_error.png`` with a reference;
* ``terrain.snapshot``: the map itself (``TerrainGrid.load_snapshot`` reads it back).

``--export-tum OUTDIR`` / ``--export-colmap OUTDIR`` instead convert the recording to the TUM
folder form or a COLMAP text model and stop.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from companion import config as config_mod
from companion.config import CompanionConfig, ConfigError
from companion.desk import plots
from companion.desk.map_metrics import (CellHeights, bin_heights, compare, dense_heights, is_colmap_points, map_cells,
                                        percentile_of, read_reference)
from companion.desk.plots import height_map
from companion.desk.recordings.layouts import open_recording, recording_config
from companion.desk.recordings.recording import Overrides, Recording, RecordingError, reason_key
from companion.desk.recordings.colmap import export_colmap
from companion.desk.recordings.tum import export_tum
from companion.method.mapper import Mapper, mean_innovation_squared
from companion.method.mapper.features import HarrisDetector
from companion.method.mapper.flow_depth import FlowRanger
from companion.method.terrain.grid import TerrainGrid

METRICS_JSON = "metrics.json"
MAP_PNG = "terrain_map.png"
ERROR_PNG = "terrain_error.png"
SNAPSHOT = "terrain.snapshot"


# --------------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------------


class ProgressBar:
    """A one-line text bar on a stream (stderr): redrawn in place on a terminal at most every
    ``interval_s``; elsewhere (a log file, a pipe) a line at every 10 %."""

    def __init__(self, total: int, stream: IO[str] | None = None, interval_s: float = 0.2, width: int = 30):
        self.total = max(0, int(total))
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = interval_s
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._t0 = time.perf_counter()
        self._last = -math.inf
        self._last_decile = -1

    def text(self, done: int) -> str:
        frac = done / self.total if self.total else 1.0
        filled = int(round(frac * self.width))
        elapsed = time.perf_counter() - self._t0
        rate = done / elapsed if elapsed > 0 else 0.0
        return f"replay [{'#' * filled}{'.' * (self.width - filled)}] {100 * frac:3.0f}% {done}/{self.total} frames {rate:6.1f} frames/s"

    def update(self, done: int) -> None:
        now = time.perf_counter()
        if self.tty:
            if now - self._last >= self.interval_s or done >= self.total:
                self._last = now
                self.stream.write("\r" + self.text(done))
                self.stream.flush()
            return
        decile = int(10 * done / self.total) if self.total else 10
        if decile > self._last_decile:
            self._last_decile = decile
            self.stream.write(self.text(done) + "\n")
            self.stream.flush()

    def close(self, done: int) -> None:
        self._last = -math.inf
        self.update(done)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# --------------------------------------------------------------------------------------------
# The replay
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Reference:
    """A reference surface in the map frame: north, east, altitude up (N,) each, and where it came from."""

    north_m: np.ndarray
    east_m: np.ndarray
    height_m: np.ndarray
    source: str
    frame: str
    bad_lines: int = 0
    statistic: str = "mean"
    min_points: int = 1


def load_reference(path: str | Path, recording: Recording, frame: str = "map", statistic: str = "mean",
                   min_points: int = 1) -> Reference:
    """Read a reference CSV. ``frame="map"``: columns are north, east, altitude up (m) in the map's
    local frame. ``frame="dataset"``: columns are x, y, z in the recording's own world frame (world
    units), converted like its poses (:class:`companion.desk.recordings.recording.WorldFrame`; for the service's
    own recordings that frame is NED, z down). ``statistic`` and ``min_points``: how the points in
    one map cell become its height (:func:`companion.desk.map_metrics.bin_heights`)."""
    try:
        percentile_of(statistic)  # a statistic that does not exist is refused before reading
    except ValueError as exc:
        raise ValueError(f"--reference-stat: {exc}") from None
    if int(min_points) < 1:
        raise ValueError(f"--reference-min-points must be at least 1, got {min_points}")
    ref = read_reference(path)
    xyz = ref.xyz
    if frame == "dataset":
        ned = recording.world.position_to_ned(xyz)
        north, east, height = ned[:, 0], ned[:, 1], -ned[:, 2]
    elif frame == "map":
        north, east, height = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    else:
        raise ValueError(f"reference frame must be 'map' or 'dataset', got {frame!r}")
    return Reference(north, east, height, str(path), frame, ref.bad_lines, statistic, int(min_points))


@dataclass(slots=True)
class ReplayResult:
    metrics: dict[str, Any]
    grid: TerrainGrid
    camera_path_ne: np.ndarray
    outputs: dict[str, Path]


def build_mapper(cfg: CompanionConfig, recording: Recording, grid: TerrainGrid, mask: np.ndarray | None = None) -> Mapper:
    """The daemon's mapper for this recording's camera: Harris detector (black borders and a static
    mask excluded, ``camera.border_px`` kept from them), terrain map as depth prior."""
    cam = recording.camera
    detector = HarrisDetector(cfg.mapper, cam.width, cam.height, border_px=cfg.camera.border_px, mask=mask)

    def depth_prior(origin: np.ndarray, rays: np.ndarray) -> np.ndarray:
        return grid.ray_range(origin, rays, cfg.mapper.prior_max_range_m)

    return Mapper(cfg.mapper, cam, recording.mount, depth_prior=depth_prior,
                  default_ground_alt_m=recording.ground_alt_m, detector=detector, border_px=cfg.camera.border_px)


JPEG_BLACK_LEVEL = 16  # measured: JPEG (quality 75) rings a black border up to ~10 grey levels near the picture
LOSSY_SUFFIXES = (".jpg", ".jpeg")


def black_level_for(path: Path, black_level: int | None) -> int:
    """The configured black level, or automatically JPEG_BLACK_LEVEL for lossy (JPEG) files and 0
    for lossless ones, whose black border is exactly 0."""
    if black_level is not None:
        return black_level
    return JPEG_BLACK_LEVEL if path.suffix.lower() in LOSSY_SUFFIXES else 0


def clamp_black(image: np.ndarray, level: int) -> np.ndarray:
    """Grey levels <= ``level`` set to 0, so that a lossy (JPEG) black border, whose pixels ring a
    few levels above 0, is recognised as border by the detector. ``level`` 0 leaves the image as is."""
    if level <= 0:
        return image
    return cv2.threshold(image, level, 255, cv2.THRESH_TOZERO)[1]


def _count(d: dict[str, int], key: str) -> None:
    d[key] = d.get(key, 0) + 1


EXIT_NOTHING_MAPPED = 3  # ran to the end, mapped nothing (1: failed, 2: bad arguments or files)


def _top(counts: dict[str, int], examples: dict[str, str]) -> tuple[int, str]:
    key = max(counts, key=counts.get)
    return counts[key], examples.get(key, key)


def nothing_mapped(m: dict[str, Any], path: Path) -> str | None:
    """One line saying why a replay mapped nothing (None when it mapped something): the count, the
    commonest cause with its numbers, and the file or setting to change."""
    if m["cells_mapped"] > 0:
        return None
    listed, ex = m["frames_listed"], m.get("reason_examples", {})
    if listed == 0:
        return f"{path}: no frame listed"
    if m["frames_unreadable"] == listed:
        n, why = _top(m["image_problems"], {})
        return f"{path}: no frame mapped: all {listed} frames unreadable ({n} of them: {why}); check the images and camera.yaml"
    if m["frames_without_nav"] == listed:
        n, why = _top(m["nav_missing_reasons"], ex)
        return f"{path}: no frame mapped: all {listed} frames without a pose ({n} of them: {why})"
    if 2 * m["frames_processed"] <= listed:  # most frames never reached the mapper: say why
        parts = []
        for label, counts in (("without a pose", m["nav_missing_reasons"]), ("unreadable", m["image_problems"]),
                              ("refused", m["refused_reasons"])):
            if counts:
                n, why = _top(counts, ex)
                parts.append(f"{sum(counts.values())} frames {label} ({n} of them: {why})")
        return f"{path}: {m['frames_processed']} of {listed} frames mapped, nothing in the map: " + "; ".join(parts)
    mp = m["mapper"]
    if m["converged_points"] == 0:
        head = (f"{path}: {m['frames_processed']} frames mapped but no feature converged ({mp['matched']} feature updates, "
                f"{mp['initialised']} features started)")
        if m["frames_processed"] >= RARE_MATCH_MIN_FRAMES and mp["matched"] < RARE_MATCH_FRACTION * max(1, mp["measurements"]):
            # Corners are found but seldom where the poses predict them from one frame to the next.
            return (f"{head}: the features rarely match from frame to frame ({mp['matched']} of {mp['measurements']} "
                    "detections): poses that do not match the images (world-to-camera where camera-to-world is expected, "
                    "quaternions in another order than x y z w, the wrong camera.yaml) or frames too far apart")
        return f"{head}: too little motion between frames, or too little texture"
    if mp["points_rejected_invalid"] >= m["converged_points"]:
        return (f"{path}: all {m['converged_points']} converged points rejected as invalid by the map: coordinates beyond "
                f"terrain.max_abs_coordinate_m, or non-finite; a geo-referenced world needs a local origin ('origin: auto' "
                f"or the origin's coordinates in meta.yaml)")
    return (f"{path}: {m['converged_points']} converged points but no cell mapped "
            f"({mp['points_rejected_outlier']} outliers, {mp['points_rejected_invalid']} invalid)")


LOOKS_UP_DEG = 5.0           # an optical axis this far above the horizon looks up
RARE_MATCH_FRACTION = 0.1    # fewer feature updates than this share of the detections: the poses do not fit the images
RARE_MATCH_MIN_FRAMES = 10   # (a good recording matches about 0.4 of them; a few frames say little)
ROLLED_DEG = 60.0            # an image whose "down" is this far from the world's down is rolled over
NEAR_NADIR_DEG = 10.0        # an optical axis this close to straight down has no "upright": any roll is a heading
IMPLAUSIBLE_FRACTION = 0.5   # warn when more of the frames than this show the same mistake
MAX_FRAME_INTERVAL_S = 60.0  # a median interval between frames above this is not a camera's


def _rolled(R_nc: np.ndarray) -> np.ndarray:
    """(K,) bool: the image is rolled more than ROLLED_DEG from upright. World down seen from the
    camera, ``d = R_nc^T (0, 0, 1)`` (paper camera frame: x optical, y right, z image down), has
    the image-plane part ``(d_y, d_z)``; upright is ``d_z > 0`` along it, and the roll is its angle
    from the image's down axis: rolled when ``d_z < cos(60 deg) |(d_y, d_z)|``. A camera within
    10 deg of straight down (``|(d_y, d_z)| < sin 10 deg``, a nadir survey camera) has no upright
    and is never counted."""
    d_y, d_z = R_nc[:, 2, 1], R_nc[:, 2, 2]
    in_plane = np.hypot(d_y, d_z)
    return (in_plane > np.sin(np.radians(NEAR_NADIR_DEG))) & (d_z < np.cos(np.radians(ROLLED_DEG)) * in_plane)


def plausibility(frame_times_s: np.ndarray, camera_alt_m: np.ndarray, R_nc: np.ndarray, ground_alt_m: float,
                 recording_path: Path) -> list[str]:
    """The likely mistakes the inputs show, one line each, naming the recording and what to check.
    ``frame_times_s`` (N,) every listed frame's time, in order; ``camera_alt_m`` (K,) and ``R_nc``
    (K, 3, 3) the camera's altitude and attitude (paper camera frame -> NED) in each mapped frame.

    * The camera below the recording's ground altitude, its image rolled more than 60 deg from
      upright (:func:`_rolled`; a camera looking straight down has no upright and is not counted),
      or its optical axis more than 5 deg above the horizon, in most frames: the signatures
      of world-to-camera poses given where camera-to-world ones are expected, of quaternions in
      another order, or of the wrong up axis (a downward camera seen through any of them).
    * Frames a median of more than a minute apart: timestamps in microseconds or nanoseconds."""
    warnings = []
    k = len(camera_alt_m)
    if k:
        R = np.asarray(R_nc, dtype=float).reshape(k, 3, 3)
        signs = (
            (np.asarray(camera_alt_m) < ground_alt_m, f"the camera is below the ground altitude ({ground_alt_m:g} m)"),
            (_rolled(R), f"the image is rolled more than {ROLLED_DEG:.0f} deg from upright"),
            (R[:, 2, 0] < -np.sin(np.radians(LOOKS_UP_DEG)), "the camera looks above the horizon"),
        )
        for bad, what in signs:
            if np.count_nonzero(bad) > IMPLAUSIBLE_FRACTION * k:
                warnings.append(
                    f"{recording_path}: {what} in {np.count_nonzero(bad)} of {k} frames: are the poses world-to-camera "
                    "(camera-to-world expected), the quaternions in another order (x y z w expected), or the up "
                    "axis wrong (meta.yaml world_up)?")
    t = np.asarray(frame_times_s, dtype=float)
    if len(t) >= 2:
        interval = float(np.median(np.diff(t)))
        if interval > MAX_FRAME_INTERVAL_S:
            warnings.append(
                f"{recording_path}: the frames are a median of {interval:,.0f} s apart: are the timestamps in "
                "microseconds or nanoseconds (seconds expected)?")
    return warnings


def run_replay(
    recording: Recording,
    cfg: CompanionConfig,
    output: str | Path,
    *,
    max_frames: int | None = None,
    reference: Reference | None = None,
    mask: np.ndarray | None = None,
    black_level: int | None = None,
    progress: bool | IO[str] = False,
    config_source: str = "defaults",
) -> ReplayResult:
    """Map ``recording`` and write metrics.json, the map figures and the map snapshot to ``output``.

    ``black_level``: grey levels treated as black border (:func:`clamp_black`); None = automatic
    per file (:func:`black_level_for`)."""
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    grid = TerrainGrid.from_config(cfg.terrain)
    mapper = build_mapper(cfg, recording, grid, mask)
    # rises seen by dense flow: the stage beside the mapper, as the service runs it
    flow = FlowRanger(cfg.mapper, recording.camera, recording.mount) if cfg.mapper.flow_on else None
    total = len(recording) if max_frames is None else min(len(recording), max_frames)
    bar = None
    if progress:
        bar = ProgressBar(total, None if progress is True else progress)

    nav_reasons: dict[str, int] = {}
    image_problems: dict[str, int] = {}
    refused: dict[str, int] = {}
    examples: dict[str, str] = {}  # reason key -> its first instance, numbers kept
    counts = dict(listed=0, processed=0, without_nav=0, unreadable=0, refused=0)
    sums = dict(measurements=0, edgels=0, edge_updates=0, matched=0, initialised=0, removed=0, dropped=0, update_rejected=0, converged_points=0,
                points_inserted=0, points_rejected_invalid=0, points_rejected_outlier=0, prior_fallback=0,
                corner_updates=0, flow_ranged=0, flow_floors=0, flow_surface_inserted=0)
    nis_sum = 0.0
    path_ne: list[np.ndarray] = []
    frame_times: list[float] = []
    camera_alt: list[float] = []
    camera_att: list[np.ndarray] = []
    mapper_s = 0.0
    t_start = time.perf_counter()
    for sample in recording.samples(limit=max_frames):
        counts["listed"] += 1
        frame_times.append(sample.t_s)
        if sample.nav is None:
            counts["without_nav"] += 1
            _count(nav_reasons, reason_key(sample.nav_problem))
            examples.setdefault(reason_key(sample.nav_problem), sample.nav_problem)
            if flow is not None:
                flow.reset()  # a pair across the gap would range with a pose nobody has
        elif sample.frame is None:
            counts["unreadable"] += 1
            _count(image_problems, sample.image_problem.split(": ", 1)[-1])
            recording.stats.note(sample.image_problem)
        else:
            image = clamp_black(sample.frame.image, black_level_for(sample.image_path, black_level))
            a = time.perf_counter()
            step = mapper.step(sample.nav, image)
            stats = grid.add_evidence(step.points, step.free_space, step.floors)
            if flow is not None:
                rises = flow.step(sample.nav, image)
                sums["flow_ranged"] += rises.n_ranged
                sums["flow_floors"] += len(rises.floors)
                sums["flow_surface_inserted"] += grid.add_flow(rises.surface, rises.floors).inserted
            mapper_s += time.perf_counter() - a
            if step.rejected_reason:
                counts["refused"] += 1
                _count(refused, reason_key(step.rejected_reason))
                examples.setdefault(reason_key(step.rejected_reason), step.rejected_reason)
            else:
                counts["processed"] += 1
                p_c, R_nc = recording.mount.camera_pose(sample.nav.position_ned_m, sample.nav.R_nb)
                path_ne.append(p_c[:2])
                camera_alt.append(float(-p_c[2]))
                camera_att.append(R_nc)
            sums["measurements"] += step.n_measurements
            sums["matched"] += step.n_matched
            sums["initialised"] += step.n_initialised
            sums["removed"] += step.n_removed
            sums["dropped"] += step.n_dropped
            sums["update_rejected"] += step.n_update_rejected
            sums["prior_fallback"] += step.n_prior_fallback
            sums["edgels"] += step.n_edgels
            sums["edge_updates"] += step.n_edge_matched
            sums["corner_updates"] += step.n_corner_updates
            nis_sum += step.innovation_nis_sum
            sums["converged_points"] += len(step.points)
            sums["points_inserted"] += stats.inserted
            sums["points_rejected_invalid"] += stats.rejected_invalid
            sums["points_rejected_outlier"] += stats.rejected_outlier
        if bar is not None:
            bar.update(counts["listed"])
    wall_s = time.perf_counter() - t_start
    if bar is not None:
        bar.close(counts["listed"])

    cells = map_cells(grid)
    camera_path = np.asarray(path_ne).reshape(-1, 2)
    stepped = counts["processed"] + counts["refused"]
    metrics: dict[str, Any] = {
        "frames_processed": counts["processed"],
        "frames_without_nav": counts["without_nav"],
        "frames_unreadable": counts["unreadable"],
        "frames_refused": counts["refused"],
        "frames_listed": counts["listed"],
        "mapper_fps": stepped / mapper_s if mapper_s > 0 else None,
        "replay_fps": counts["listed"] / wall_s if wall_s > 0 else None,
        "wall_s": wall_s,
        "converged_points": sums["converged_points"],
        "cells_mapped": len(cells),
        "map": {
            "tiles": len(grid),
            "area_m2": grid.observed_area_m2(),
            "cell_size_m": grid.cell_size_m,
            "height_min_m": float(cells.height.min()) if len(cells) else None,
            "height_max_m": float(cells.height.max()) if len(cells) else None,
            "memory_bytes": grid.memory_bytes(),
            "frame_shift_m": grid.frame_shift_m,
            "frame_shifts": grid.frame_shifts,
        },
        "mapper": sums | {"n_active_end": mapper.db.n_active,
                          "innovation_nis_mean": mean_innovation_squared(nis_sum, sums["corner_updates"]),
                          "point_covariance_scale_end": mapper.point_covariance_scale},
        "nav_missing_reasons": nav_reasons,
        "reason_examples": examples,
        "warnings": plausibility(np.asarray(frame_times), np.asarray(camera_alt), np.asarray(camera_att),
                                 recording.ground_alt_m, recording.path),
        "image_problems": image_problems,
        "refused_reasons": refused,
        "recording": recording.describe(),
        "config": {
            "source": config_source,
            "parameterisation": cfg.mapper.parameterisation,
            "max_features": cfg.mapper.max_features,
            "max_detections": cfg.mapper.max_detections,
            "border_px": cfg.camera.border_px,
            "black_level": "auto" if black_level is None else black_level,
            "static_mask": mask is not None,
            "cell_size_m": cfg.terrain.cell_size_m,
        },
    }
    outputs: dict[str, Path] = {}
    if reference is not None:
        ref_cells = bin_heights(reference.north_m, reference.east_m, reference.height_m, grid.cell_size_m,
                                reference.statistic, reference.min_points)
        metrics["reference"] = compare(cells, ref_cells) | {
            "source": reference.source, "frame": reference.frame, "statistic": reference.statistic,
            "min_points": reference.min_points,
            "points": int(len(reference.height_m)), "bad_lines": reference.bad_lines,
        }  # fmt: skip
        outputs["error_png"] = _error_figure(output / ERROR_PNG, cells, ref_cells, grid.cell_size_m, camera_path, metrics["reference"])

    outputs["map_png"] = _map_figure(output / MAP_PNG, cells, grid.cell_size_m, camera_path, recording, metrics)
    grid.save_snapshot(output / SNAPSHOT)
    outputs["snapshot"] = output / SNAPSHOT
    metrics["outputs"] = {k: str(v) for k, v in outputs.items()}
    path = output / METRICS_JSON
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(metrics, indent=2, default=_json_default) + "\n")
    tmp.replace(path)
    outputs["metrics"] = path
    return ReplayResult(metrics, grid, camera_path, outputs)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _map_figure(path: Path, cells: CellHeights, cell_m: float, camera_path: np.ndarray, recording: Recording,
                metrics: dict[str, Any]) -> Path:
    """The height map, north up, with the camera path. The colour range is the 1st-99th percentile
    of the cell heights (a few wild cells would otherwise flatten every other colour); cells
    beyond it take the end colours."""
    heights, n0, e0, c = dense_heights(cells, cell_m, include_ne=camera_path)
    lo, hi = (np.percentile(cells.height, [1, 99]) if len(cells) else (None, None))
    title = f"{recording.kind} replay: {len(cells)} cells, {metrics['frames_processed']} frames"
    return height_map(path, heights, n0, e0, c, title, paths=[(camera_path, "camera path", (40, 40, 220))],
                      vmin=None if lo is None else float(lo), vmax=None if hi is None else float(hi))


def _error_figure(path: Path, cells: CellHeights, ref: CellHeights, cell_m: float, camera_path: np.ndarray,
                  stats: dict[str, Any]) -> Path:
    _, i_map, i_ref = np.intersect1d(cells.keys, ref.keys, assume_unique=True, return_indices=True)
    err = CellHeights(cells.ci[i_map], cells.cj[i_map], cells.height[i_map] - ref.height[i_ref])
    heights, n0, e0, c = dense_heights(err, cell_m, include_ne=camera_path)
    span = float(np.percentile(np.abs(err.height), 95)) if len(err) else 1.0
    span = max(span, 0.1)
    rmse = stats.get("rmse_m")
    title = f"map - ref: RMSE {rmse:.2f} m" if rmse is not None else "map - ref: no common cell"
    return height_map(path, heights, n0, e0, c, title, paths=[(camera_path, "camera path", (40, 40, 220))], vmin=-span, vmax=span)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="DIR", help="recording folder: companion --record, TUM folder or EuRoC (mav0)")
    p.add_argument("--output", "-o", metavar="OUT", help="output folder (default ./replay-<name of DIR>)")
    p.add_argument("--config", metavar="FILE", help="YAML configuration (mapper, terrain, nav, camera.border_px); "
                   "default: the recording's own (companion) or the built-in defaults")
    p.add_argument("--format", choices=("auto", "companion", "tum", "euroc", "colmap"), default="auto", help="recording layout")
    p.add_argument("--parameterisation", choices=("inverse_depth", "cartesian"), help="override mapper.parameterisation")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after the first N listed frames")
    p.add_argument("--reference", metavar="FILE", help="reference surface: x,y,z text (DSM grid or point cloud), a .ply "
                                                        "point cloud or a COLMAP points3D.txt")
    p.add_argument("--reference-frame", choices=("map", "dataset"),
                   help="map: north,east,altitude-up in the map frame; dataset: x,y,z in the recording's world frame "
                        "(default: dataset for a COLMAP points3D.txt, map otherwise)")
    p.add_argument("--reference-stat", default="mean", metavar="STAT",
                   help="how reference points in one map cell become its height: mean (default), median, max, or "
                        "pNN, a percentile (p90: the top surface of a point cloud without its single noisy points)")
    p.add_argument("--reference-min-points", type=int, default=1, metavar="N",
                   help="map cells holding fewer reference points are left out of the comparison (default 1)")
    p.add_argument("--pose-sigma-m", type=float, metavar="M", help="pose position sigma (TUM/EuRoC; overrides metadata)")
    p.add_argument("--pose-sigma-deg", type=float, metavar="DEG", help="pose attitude sigma (TUM/EuRoC; overrides metadata)")
    p.add_argument("--ground-alt-m", type=float, metavar="M", help="ground altitude assumed before the map knows")
    p.add_argument("--mask", metavar="FILE.png", help="static mask image (non-zero = usable pixels)")
    p.add_argument("--black-level", type=int, default=None, metavar="L",
                   help=f"grey levels <= L count as black border (default: {JPEG_BLACK_LEVEL} for JPEG files, 0 otherwise)")
    p.add_argument("--export-tum", metavar="OUTDIR", help="convert the recording to the TUM folder form and stop")
    p.add_argument("--export-colmap", metavar="OUTDIR", help="convert the recording to a COLMAP text model (+ images, "
                                                               "meta.yaml, timestamps.txt) and stop")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def _fail(message: str) -> int:
    print(f"companion replay: {message}", file=sys.stderr)
    return 2


def main(args: argparse.Namespace) -> int:
    plots.require()  # the figures need the desk extra: say so before the replay, not after it
    path = Path(args.recording).expanduser()
    if args.max_frames is not None and args.max_frames < 1:
        return _fail(f"--max-frames must be at least 1, got {args.max_frames}")
    if args.black_level is not None and not 0 <= args.black_level <= 254:
        return _fail(f"--black-level must be in 0..254, got {args.black_level}")
    for name in ("pose_sigma_m", "pose_sigma_deg"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value >= 0):
            return _fail(f"--{name.replace('_', '-')} must be a finite number >= 0, got {value}")
    try:
        if args.config:
            cfg, source = config_mod.load_config(args.config), str(args.config)
        else:
            own = recording_config(path) if path.is_dir() else None
            cfg, source = (own, f"{path}/meta.yaml") if own is not None else (CompanionConfig(), "defaults")
        if args.parameterisation:
            cfg = config_mod.replace(cfg, **{"mapper.parameterisation": args.parameterisation})
        overrides = Overrides(args.pose_sigma_m, args.pose_sigma_deg, args.ground_alt_m)
        recording = open_recording(path, cfg, kind=args.format, overrides=overrides)
    except (ConfigError, RecordingError) as exc:
        return _fail(str(exc))
    except OSError as exc:  # permissions, a file vanishing under us
        return _fail(f"{exc.filename or path}: {exc.strerror or exc}")

    for target, export in ((args.export_tum, export_tum), (args.export_colmap, export_colmap)):
        if not target:
            continue
        try:
            counts = export(recording, target, limit=args.max_frames)
        except (FileExistsError, OSError, ValueError) as exc:
            return _fail(str(exc))
        print(f"exported {counts['written']} frames to {target} "
              f"({counts['without_nav']} without navigation, {counts['missing_image']} missing images left out)")
        return 0 if counts["written"] else EXIT_NOTHING_MAPPED

    try:
        frame = args.reference_frame or ("dataset" if is_colmap_points(args.reference or "") else "map")
        reference = (load_reference(args.reference, recording, frame, args.reference_stat,
                                    args.reference_min_points) if args.reference else None)
    except ValueError as exc:
        return _fail(str(exc))
    mask = None
    if args.mask:
        mask = cv2.imread(args.mask, cv2.IMREAD_GRAYSCALE)
        cam = recording.camera
        if mask is None:
            return _fail(f"--mask {args.mask}: cannot be read as an image")
        if mask.shape != (cam.height, cam.width):
            return _fail(f"--mask {args.mask}: {mask.shape[1]}x{mask.shape[0]}, the camera is {cam.width}x{cam.height}")

    output = Path(args.output) if args.output else Path.cwd() / f"replay-{path.resolve().name}"
    result = run_replay(recording, cfg, output, max_frames=args.max_frames, reference=reference, mask=mask,
                        black_level=args.black_level, progress=not args.no_progress, config_source=source)
    m = result.metrics
    fps = m["mapper_fps"]
    print(f"{m['frames_processed']} of {m['frames_listed']} frames mapped ({m['frames_without_nav']} without navigation, "
          f"{m['frames_unreadable']} unreadable, {m['frames_refused']} refused)"
          + (f"; mapper {fps:.1f} frames/s" if fps else ""))
    print(f"{m['converged_points']} converged points, {m['cells_mapped']} cells mapped -> {output}")
    if m["map"]["frame_shifts"]:
        print(f"map moved {m['map']['frame_shifts']} times to follow the navigation's vertical frame, "
              f"{m['map']['frame_shift_m']:+.2f} m in all (docs/terrain.md, \"The navigation's frame\")")
    nis = m["mapper"]["innovation_nis_mean"]
    if nis is not None:
        print(f"filter consistency: mean innovation squared {nis:.2f} over {m['mapper']['corner_updates']} corner updates "
              f"(2 = the covariances are the errors; below: conservative; above: overconfident; docs/replay.md); "
              f"points' covariance scaled by {m['mapper']['point_covariance_scale_end']:.2f} at the end")
    for warning in m["warnings"]:
        print(f"companion replay: warning: {warning}", file=sys.stderr)
    why = nothing_mapped(m, path)
    if why is not None:
        print(f"companion replay: {why}", file=sys.stderr)
        return EXIT_NOTHING_MAPPED
    ref = m.get("reference")
    if ref is not None:
        if ref["rmse_m"] is None:
            print(f"reference: no cell in common ({ref['cells_reference']} reference cells)")
        else:
            print(f"reference: RMSE {ref['rmse_m']:.3f} m, bias {ref['bias_m']:+.3f} m over {ref['cells_compared']} cells "
                  f"(coverage {100 * ref['coverage']:.1f} %)")
    return 0
