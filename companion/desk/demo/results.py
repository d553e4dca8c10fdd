"""The demo's results: what each run and the comparison measured (``metrics.json``, docs/demo.md),
the lines printed at the end, and each run saved so that ``--replot`` rebuilds the report."""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from companion.desk import report
from companion.desk.demo.flight import LAP_RADIUS_M, RunRecord
from companion.desk.demo.pilot import TruthLog

DETECTION_FRACTION = 0.5       # the obstacle counts as mapped once half its textured height is


def _num(x: Any, digits: int = 3):
    """JSON-safe number: None for NaN/inf."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def warning_needed_s(world, obstacle) -> float:
    """The law's time (s) to climb from the nominal altitude to the textured height plus clearance
    (the demo flies the law's default acceleration and climb-rate limits)."""
    from companion.method.avoidance import stopping_time
    from companion.config import AvoidanceConfig

    a = AvoidanceConfig()
    gain = obstacle.textured_height_m + float(world.clearance_m) - float(world.circuit.altitude_agl_m)
    return stopping_time(gain, a.accel_mps2, a.max_climb_mps)


def run_metrics(rec: RunRecord, world, obstacle, clearance_m: float) -> dict[str, Any]:
    """The figures of one run (the ``runs.<parameterisation>`` entry of metrics.json)."""
    t, ne, alt = rec.truth.arrays()
    det_t = np.array([d[0] for d in rec.detection], float)
    det_h = np.array([d[1] for d in rec.detection], float)
    detected_t = report.first_detection_time(det_t, det_h, DETECTION_FRACTION * obstacle.textured_height_m)
    ground = report.ground_around(obstacle.footprint_ne_m, world.terrain_height)
    laps = []
    starts = [0] + rec.lap_ends[:-1]
    for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
        sl = slice(s, e + 1)
        crossing = report.min_clearance_over_footprint(t[sl], ne[sl], alt[sl], obstacle.footprint_ne_m, world.terrain_height)
        mapped = report.mapped_height_over_footprint(rec.lap_maps[k], obstacle.footprint_ne_m, ground_m=ground)
        err = report.map_error(rec.lap_maps[k], world.terrain_height)
        agl = alt[sl] - world.terrain_height(ne[sl, 0], ne[sl, 1])
        laps.append({
            "lap": k + 1,
            "min_clearance_m": _num(crossing.min_clearance_m),
            "mapped_obstacle_height_m": _num(mapped.height_m),
            "mapped_obstacle_max_m": _num(mapped.max_m),
            "mapped_obstacle_cells": mapped.cells,
            "start_t_s": _num(t[s], 2), "end_t_s": _num(t[e], 2),
            "crossing_t_s": _num(crossing.entered_t_s, 2),
            "min_clearance_at_ne_m": None if crossing.at_ne_m is None else [_num(v, 2) for v in crossing.at_ne_m],
            "mapped_before_lap": bool(np.isfinite(detected_t) and detected_t <= t[s]),
            "mapped_before_crossing": bool(np.isfinite(detected_t) and np.isfinite(crossing.entered_t_s)
                                           and detected_t <= crossing.entered_t_s),
            "warning_s": _num(crossing.entered_t_s - detected_t, 2),
            "max_alt_m": _num(np.max(alt[sl])),
            "max_height_above_terrain_m": _num(np.max(agl)),
            "cruise_height_over_flat_m": _num(report.height_over_flat_ground(ne[sl], alt[sl], world.terrain_height)[0]),
            "map_rmse_m": _num(err.rmse_m),
            "service_lap_end_t_s": _num(rec.service_laps[k], 2) if k < len(rec.service_laps) else None,
        })
    final_err = report.map_error(rec.final_map, world.terrain_height)
    textured_err = report.map_error(rec.final_map, lambda n, e: world.terrain_height(n, e, textured_only=True))
    st = rec.status or {}
    mapper, cam, control = st.get("mapper") or {}, st.get("camera") or {}, st.get("control") or {}
    return {
        "laps": laps,
        "map_rmse_m": _num(final_err.rmse_m),
        "map_error": {
            "cells": final_err.cells, "bias_m": _num(final_err.bias_m), "within_1m": _num(final_err.within_1m),
            "p95_abs_m": _num(final_err.p95_abs_m), "max_abs_m": _num(final_err.max_abs_m),
            "cells_over_3m_high": final_err.over_3m, "rmse_vs_textured_m": _num(textured_err.rmse_m),
        },
        "first_detection_t_s": _num(detected_t, 2),
        "complete": rec.complete,
        "problem": rec.problem,
        "wall_time_s": _num(rec.wall_s, 1),
        "sim_time_s": _num(t[-1] if len(t) else math.nan, 1),
        "avoidance_engaged_s": _num(rec.engaged_time_s, 1),
        "frames": cam.get("frames"),
        "frames_mapped": mapper.get("frames_mapped"),
        "frames_dropped": cam.get("queue_dropped"),
        "lockstep": cam.get("lockstep"),  # frames simulated time waited for (None: paced by the wall clock)
        "points_converged": mapper.get("points_converged"),
        "map_tiles": (st.get("map") or {}).get("tiles"),
        "service": {
            "mapper_step_ms": mapper.get("step_ms"),
            "flow": mapper.get("flow"),
            "frame_to_setpoint_ms": control.get("frame_to_setpoint_ms"),
            "control_jitter_ms": control.get("jitter_ms"),
            "control_rate_hz": control.get("rate_hz"),
            "lap_count": control.get("lap"),
            "health": st.get("health"), "problems": st.get("problems"),
            "exit": rec.daemon_exit,
        },
        "simulator_exit": rec.sim_exit,
        "ground_station": rec.ground,
    }


def write_trajectory(rec: RunRecord, path: Path) -> Path:
    t, ne, alt = rec.truth.arrays()
    lap = np.zeros(len(t), int)
    for end in rec.lap_ends:
        lap[end + 1:] += 1
    with open(path, "w") as f:
        f.write("t_s,north_m,east_m,alt_m,lap\n")
        for row in zip(t, ne[:, 0], ne[:, 1], alt, lap + 1):
            f.write(f"{row[0]:.3f},{row[1]:.3f},{row[2]:.3f},{row[3]:.3f},{row[4]}\n")
    return path


OPTION_KEYS = ("scenario", "laps", "speedup", "no_lockstep", "seed", "no_avoid", "camera_rate", "config", "set")


def save_record(rec: RunRecord, path: Path, opts=None) -> Path:
    """Everything the report needs from one run, in one ``.npz`` (``--replot`` reads it back)."""
    t, ne, alt = rec.truth.arrays()
    arrays: dict[str, Any] = {"t_s": t, "ne_m": ne, "alt_m": alt, "lap_ends": np.asarray(rec.lap_ends, np.int64),
                              "detection": np.asarray(rec.detection, float).reshape(-1, 2)}
    for k, m in enumerate(rec.lap_maps):
        arrays[f"lap{k}_height"], arrays[f"lap{k}_count"] = m.height.astype(np.float32), m.count.astype(np.uint32)
        arrays[f"lap{k}_origin"] = np.array([m.north0_m, m.east0_m, m.cell_m])
    meta = {k: getattr(rec, k) for k in ("parameterisation", "status", "engaged_time_s", "wall_s", "complete", "problem",
                                         "daemon_exit", "sim_exit", "ground", "service_laps")}
    if opts is not None:
        meta["options"] = {k: getattr(opts, k, None) for k in OPTION_KEYS}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load_record(path: Path) -> RunRecord:
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        truth = TruthLog(list(z["t_s"]), list(z["ne_m"][:, 0]), list(z["ne_m"][:, 1]), list(z["alt_m"]))
        maps = []
        k = 0
        while f"lap{k}_height" in z:
            n0, e0, c = (float(v) for v in z[f"lap{k}_origin"])
            maps.append(report.MapRaster(z[f"lap{k}_height"].astype(float), z[f"lap{k}_count"].astype(np.int64), n0, e0, c))
            k += 1
        rec = RunRecord(meta.pop("parameterisation"), truth, [int(i) for i in z["lap_ends"]], maps,
                        detection=[(float(a), float(b)) for a, b in z["detection"]])
    rec.options = meta.pop("options", None)
    for key, value in meta.items():
        setattr(rec, key, value)
    if maps:
        rec.final_map = maps[-1]
    return rec


def build_metrics(records: dict[str, RunRecord], world, obstacle, opts, wall_s: float) -> dict[str, Any]:
    clearance = float(world.clearance_m)
    runs = {p: run_metrics(r, world, obstacle, clearance) for p, r in records.items()}
    verdicts = {}
    for p, m in runs.items():
        other = [q for q in runs if q != p]
        other_laps = runs[other[0]]["laps"] if (p == "inverse_depth" and other) else None
        laps = [{k: (math.nan if v is None else v) for k, v in lap.items()} for lap in m["laps"]]
        olaps = None if other_laps is None else [{k: (math.nan if v is None else v) for k, v in lap.items()}
                                                 for lap in other_laps]
        verdicts[p] = {k: (_num(v) if isinstance(v, float) else v)
                       for k, v in report.criteria(laps, clearance, obstacle.textured_height_m, olaps,
                                                   float(obstacle.height_m),
                                                   float(world.circuit.altitude_agl_m)).items()}
    return {
        "schema": "companion.demo/1",
        "clearance_m": clearance,
        "obstacle_textured_height_m": float(obstacle.textured_height_m),
        "obstacle": {"name": obstacle.name, "height_m": float(obstacle.height_m),
                     "footprint_ne_m": obstacle.footprint_ne_m.tolist()},
        "runs": runs,
        "criteria": verdicts,
        "warning_needed_s": _num(warning_needed_s(world, obstacle), 2),
        "paper": {"mapped_fraction_of_height": report.PAPER_MAPPED_FRACTION,
                  "note": "Magree, Mooney, Johnson, section IV: the 40 ft structure (texture to ~30 ft) was mapped at about 30 ft"},
        "definitions": {
            "cruise_height_over_flat_m": "median (altitude - true terrain) over the lap where the terrain is flat within 15 m (the nominal altitude above the mapped ground: docs/avoidance.md, \"The ground the nominal altitude stands on\")",
            "min_clearance_m": "least (altitude - true terrain) while the true position is over the obstacle's footprint, per lap",
            "mapped_obstacle_height_m": "95th percentile of the mapped heights of the footprint cells (grown by one cell) "
                                        "holding >= 2 points, in the ground station's map at the lap's end",
            "first_detection_t_s": f"first time the mapped obstacle height reached {DETECTION_FRACTION:g} x the textured height",
            "warning_s": "the lap's crossing minus the first detection: at least warning_needed_s (the law's time to climb "
                         "from the nominal altitude to textured height + clearance) lets the law climb smoothly; every lap is "
                         "judged for clearance whatever its warning",
            "map_rmse_m": "RMSE of every observed cell of the final map against the highest true terrain over the cell",
            "laps": f"cut where the true trajectory comes back within {LAP_RADIUS_M:g} m of the first waypoint after the others",
        },
        "scenario": opts.scenario,
        "laps_requested": opts.laps,
        "speedup": opts.speedup,
        "lockstep": not getattr(opts, "no_lockstep", False),
        "camera_rate_hz": opts.camera_rate,
        "seed": opts.seed,
        "avoidance_enabled": not opts.no_avoid,
        "wall_time_s": round(wall_s, 1),
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
    }


DROPPED_WARN = 0.05  # a larger share of camera frames dropped by the service is worth a word


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A few lines for the terminal: per lap, mapped height and least clearance; a warning when the
    service could not keep up with the camera."""
    out = [f"obstacle textured to {metrics['obstacle_textured_height_m']:g} m (roof {metrics['obstacle']['height_m']:g} m); "
           f"clearance {metrics['clearance_m']:g} m; the paper mapped ~{100 * report.PAPER_MAPPED_FRACTION:.0f}% of the roof height"]
    for p, run in metrics["runs"].items():
        laps = "  ".join(
            f"lap {lap['lap']}: height {_fmt(lap['mapped_obstacle_height_m'])} m, clearance {_fmt(lap['min_clearance_m'])} m"
            for lap in run["laps"])
        out.append(f"{p:>13}: {laps or 'no complete lap'}; map RMSE {_fmt(run['map_rmse_m'])} m"
                   + (f"  [{run['problem']}]" if run["problem"] else ""))
        frames, dropped = run.get("frames") or 0, run.get("frames_dropped") or 0
        if frames and dropped > DROPPED_WARN * frames:
            out.append(f"{'':>13}  warning: the service dropped {100 * dropped / frames:.0f}% of the camera frames "
                       f"(busy machine or --speedup {metrics['speedup']:g} too high for it): try a lower --speedup")
        flow = (run.get("service") or {}).get("flow") or {}
        flow_dropped = flow.get("queue_dropped") or 0
        if frames and flow.get("on") and flow_dropped > DROPPED_WARN * frames:
            out.append(f"{'':>13}  warning: the dense flow dropped {100 * flow_dropped / frames:.0f}% of the camera frames "
                       f"(busy machine or --speedup {metrics['speedup']:g} too high for it): try a lower --speedup")
    return out


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.1f}"
