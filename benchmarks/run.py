"""``python -m benchmarks.run [--quick]``: every performance figure in one run.

Prints tables (median and p99 over repeated runs, the machine) and writes
``benchmarks/results.json``. Single-core figures run pinned to core 0 with OpenCV single-threaded;
the daemon run gives the daemon core 1 and the simulator core 0. Nothing here asserts: a target
that is missed is printed as missed. See docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path


def _pin_before_numpy() -> str:
    """Pin this process to core 0 before NumPy loads OpenBLAS. Pinned after the import, OpenBLAS
    keeps the two threads it started for two cores, which then spin against each other on one
    (measured: a (300, 81) @ (81, 470) float32 product, the mapper's appearance correlation,
    0.26 ms -> 0.62 ms median and 19 ms p99)."""
    if "numpy" in sys.modules:
        return "after NumPy was loaded (BLAS may run two threads on one core)"
    try:
        os.sched_setaffinity(0, {0})
    except (AttributeError, OSError) as exc:
        return f"not pinned ({exc})"
    return "before NumPy was loaded"


PINNING = _pin_before_numpy()

from benchmarks import common, daemon_bench, map_bench, mapper_bench  # noqa: E402 - NumPy after pinning
from benchmarks.common import fmt, table  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results.json"

# key -> (target, "min" = at least / "max" = at most, unit, what)
TARGETS = {
    "mapper_fps_50": (250.0, "min", "frames/s", "mapper step + grid insert, 640x480, 50 features, one core"),
    "mapper_fps_300": (100.0, "min", "frames/s", "mapper step + grid insert, 640x480, 300 features, one core"),
    "floor_ratio": (2.5, "max", "x", "mapper step + grid insert / cv2.cornerHarris alone, same frames (50 features)"),
    "frame_to_setpoint_p99_ms": (15.0, "max", "ms", "daemon mapping at 30 fps: frame exposure stamp -> setpoint, p99"),
    "control_jitter_p99_ms": (5.0, "max", "ms", "daemon control loop at 20 Hz: lateness of the tick, p99"),
    "grid_insert_1000_ms": (1.0, "max", "ms", "TerrainGrid.insert of 1,000 converged points (median, mapped area)"),
    "avoidance_query_ms": (0.5, "max", "ms", "PullUpLaw.command, 100 m look-ahead over a mapped area (median)"),
    "batched_vs_loop_speedup": (None, "min", "x", "match+update, batched vs per-feature loop, 50 features (median)"),
}


@dataclass(frozen=True)
class Plan:
    """How much of everything a run measures (``--quick`` or the full run)."""

    quick: bool
    frames: int  # rendered frames (the headline run uses all of them)
    repeats: int  # repeats of the headline run
    scale_frames: int  # frames per feature count in the scaling table
    feature_counts: tuple[int, ...]
    profile_frames: int
    match_update_frames: dict  # features -> frames for the batched / loop comparison
    whole_step_frames: dict
    insert_repeats: int
    query_repeats: int
    memory_shapes_m: tuple[tuple[float, float], ...]
    map_sides_m: tuple[float, ...]
    map_size_frames: int
    daemon_seconds: float
    daemon_runs: int  # repeats of the daemon run with the streamed camera (headline: median of the p99s)

    @classmethod
    def make(cls, quick: bool) -> "Plan":
        if quick:
            return cls(True, 90, 1, 60, (10, 50, 100, 300, 500), 60, {50: 60, 300: 30}, {50: 40}, 30, 100,
                       ((100, 100), (1000, 1000), (10000, 100)), (0.0, 1000.0), 40, 8.0, 1)
        return cls(False, 600, 2, 300, (10, 25, 50, 100, 200, 300, 400, 500), 200, {50: 300, 300: 120},
                   {50: 150, 300: 60}, 200, 500, ((100, 100), (316, 316), (1000, 1000), (10000, 100)),
                   (0.0, 300.0, 1000.0, 2000.0), 150, 30.0, 3)


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="short run (under a minute): fewer frames and repeats")
    p.add_argument("--out", default=str(RESULTS), help="results file (default benchmarks/results.json)")
    p.add_argument("--no-daemon", action="store_true", help="skip the daemon run (simulator + companion run)")
    p.add_argument("--daemon-seconds", type=float, help="daemon run length after take-off (default 30, quick 8)")
    p.add_argument("--daemon-runs", type=int, help="daemon runs with the streamed camera; the headline figures are "
                                                   "the median of their p99s (default 3, quick 1)")
    p.add_argument("--daemon-experiments", action="store_true",
                   help="also run the daemon with its mapper in a child process, and with Python's default GIL "
                        "switch interval (5 ms, against the daemon's 1 ms): what each does to the control jitter")
    p.add_argument("--profile", action="store_true", help="also print cProfile's top functions of the mapper step")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    plan = Plan.make(args.quick)
    t_start = time.perf_counter()
    pinned = common.pin_one_core(0)
    machine = common.machine_info()
    print(f"companion benchmarks ({'quick' if plan.quick else 'full'}): {machine['cpu']}, {machine['cpus']} CPUs, "
          f"Python {machine['python']}, NumPy {machine['numpy']}, OpenCV {machine['opencv']}")
    print(f"single-core figures on core 0 (pinned: {pinned}, {PINNING}), cv2 threads {machine['opencv_threads']}, "
          f"load average {machine['loadavg']}")
    machine["pinning"] = PINNING
    timings: dict[str, float] = {}
    details: dict = {}
    last = time.perf_counter()
    sections = [
        ("flight", lambda: flight_section(plan)),
        ("mapper", lambda: mapper_section(flight, plan)),
        ("flow", lambda: flow_section(flight, plan)),
        ("scaling", lambda: scaling_section(flight, plan)),
        ("profile", lambda: profile_section(flight, plan, args.profile)),
        ("batched_vs_loop", lambda: loop_section(flight, plan)),
        ("map", lambda: map_section(flight, plan)),
        ("daemon", lambda: daemon_section(plan, args)),
    ]
    flight = None
    for name, run in sections:
        result = run()
        if name == "flight":
            flight, result = result
        details[name] = result
        now = time.perf_counter()
        timings[name] = round(now - last, 1)
        last = now
    values, extra = headline_values(details)
    print_targets(values, extra)
    out = {**values, **extra,
           "targets": {k: {"target": t, "kind": kind, "unit": u, "what": w, "measured": values[k]}
                       for k, (t, kind, u, w) in TARGETS.items()},
           "mode": "quick" if plan.quick else "full", "machine": machine,
           "loadavg_at_end": common.machine_info()["loadavg"],
           "run_seconds": round(time.perf_counter() - t_start, 1), "section_seconds": timings,
           "generated_unix_s": round(time.time(), 1), "details": details}
    Path(args.out).write_text(json.dumps(out, indent=1, default=_json_default))
    print(f"\nwrote {args.out} ({out['run_seconds']:.0f} s: " + ", ".join(f"{k} {v:g}" for k, v in timings.items()) + ")")
    return 0


# ------------------------------------------------------------------------------------------------
# Sections, in the order they run; each prints its tables and returns what goes in the results
# ------------------------------------------------------------------------------------------------


def flight_section(plan: Plan):
    t0 = time.perf_counter()
    flight = common.render_flight(plan.frames)
    r = common.summary(flight.render_ms)
    end = common.START_NORTH_M + common.SPEED_MPS * plan.frames / common.RATE_HZ
    print(f"\nrendered {len(flight)} frames 640x480 at {common.RATE_HZ:g} Hz along the default circuit "
          f"(north {common.START_NORTH_M:g} -> {end:.0f} m) in {time.perf_counter() - t0:.1f} s "
          f"(render median {fmt(r['median'])} ms)")
    return flight, {"frames": len(flight), "rate_hz": common.RATE_HZ, "render_ms": r}


NO_MAP = "50 no map"  # the 50-feature mapper without the terrain map, beside the headline


def mapper_section(flight, plan: Plan) -> dict:
    """Frames per second at 50 and 300 features and the distance to the Harris floor.

    The step is the target's: detect + match + update + initialise + grid insert. Each mapper
    reads its depth prior from its own terrain map and inserts its converged points into it, as
    the daemon does (a fresh map per repeat). The 50-feature mapper without a map (flat-ground
    prior, no insert) runs interleaved beside them, for what the map adds."""
    print("\n== Mapper step (detect + match + update + initialise + grid insert), one core ==")
    variants = {n: mapper_bench.variant(flight, n, grid=mapper_bench.fresh_grid(flight)) for n in (50, 300)}
    variants[NO_MAP] = mapper_bench.variant(flight, 50)
    headline = mapper_bench.run_interleaved(flight, variants, repeats=plan.repeats, with_floor=True)
    rows = []
    for n, h in headline.items():
        h["n_features"] = 50 if n == NO_MAP else n
        rows.append([str(n), h["step_ms"]["median"], h["step_ms"]["p99"], h["fps"], h["step_cpu_ms"]["median"],
                     h["step_cpu_ms"]["p99"], h["fps_cpu"], h["measurements"], h["matched"], h["active"],
                     h["points_per_frame"], h["floor_ratio"]])
    print(table(["features", "median ms", "p99 ms", "frames/s", "cpu med ms", "cpu p99", "cpu frames/s",
                 "meas/frame", "matched", "stored", "points out", "/ Harris"], rows))
    print("  (wall clock; 'cpu' = this thread's CPU time, which leaves out what other processes on this shared "
          f"machine took from the core; '{NO_MAP}': the 50-feature step without the map's prior and insert)")
    h50 = headline[50]
    print(f"floor: cv2.cornerHarris alone median {fmt(h50['harris_ms']['median'])} ms (p99 {fmt(h50['harris_ms']['p99'])}); "
          f"step / Harris = {fmt(h50['floor_ratio'])} (median of per-frame ratios {fmt(h50['floor_ratio_per_frame_median'])}; "
          f"CPU time: Harris {fmt(h50['harris_cpu_ms']['median'])} ms, ratio {fmt(h50['floor_ratio_cpu'])}); "
          f"without the map {fmt(headline[NO_MAP]['floor_ratio'])}")
    return {str(n): _public(h) for n, h in headline.items()}


def flow_section(flight, plan: Plan) -> dict:
    """The dense-flow stage (``FlowRanger.step``, docs/mapper.md, "Rises seen by dense flow") frame by
    frame beside the 50-feature mapper step, interleaved on the same core, with the configured
    ``mapper.flow_every_frames``: the time of a measured frame, the mean over all frames (a frame
    not measured is stored only), and the ratio of the means to the mapper's. The service runs the
    stage in a thread of its own, off the path from a frame to its setpoint."""
    from companion.method.mapper.flow_depth import FlowRanger

    cfg = flight.cfg.mapper
    every = cfg.flow_every_frames
    print(f"\n== Dense-flow stage beside the mapper (every {every} frame(s) measured, pairs {cfg.flow_frames_apart} "
          "frames apart), one core, interleaved ==")
    measured, stored, mapper_ms = [], [], []
    for _ in range(plan.repeats):
        ranger = FlowRanger(cfg, flight.camera, flight.mount)
        mapper = mapper_bench.new_mapper(flight, 50)
        for k in range(len(flight)):
            t0 = time.perf_counter()
            mapper.step(flight.navs[k], flight.images[k])
            t1 = time.perf_counter()
            step = ranger.step(flight.navs[k], flight.images[k])
            t2 = time.perf_counter()
            mapper_ms.append((t1 - t0) * 1e3)
            (measured if step.measured else stored).append((t2 - t1) * 1e3)
    per_frame = (sum(measured) + sum(stored)) / max(1, len(measured) + len(stored))
    m = common.summary(mapper_ms)
    out = {"every_frames": every, "measured_ms": common.summary(measured), "stored_ms": common.summary(stored),
           "mean_per_frame_ms": per_frame, "mapper_50_ms": m,
           "ratio_to_mapper": per_frame / m["mean"], "frames_per_s": 1e3 / per_frame}
    print(table(["stage", "median ms", "p99 ms", "mean ms / frame", "frames/s"],
                [["flow, measured frames", out["measured_ms"]["median"], out["measured_ms"]["p99"], None, None],
                 ["flow, every frame", None, None, per_frame, out["frames_per_s"]],
                 ["mapper, 50 features", m["median"], m["p99"], m["mean"], 1e3 / m["mean"]]]))
    print(f"  flow / mapper (means per frame, same run): {fmt(out['ratio_to_mapper'])}; the service runs the flow in a "
          "thread of its own, so its time is not in the mapper's frames/s nor in frame -> setpoint")
    return out


def scaling_section(flight, plan: Plan) -> list:
    print(f"\n== Time per frame against the number of features ({plan.scale_frames} frames, one pass each, interleaved) ==")
    runs = mapper_bench.run_interleaved(flight, {n: mapper_bench.variant(flight, n) for n in plan.feature_counts},
                                        repeats=1, frames=plan.scale_frames)
    scaling = [{"n_features": n, **_public(s)} for n, s in runs.items()]
    print(table(["features", "median ms", "p99 ms", "frames/s", "cpu med ms", "cpu frames/s", "meas/frame", "matched",
                 "stored"],
                [[str(s["n_features"]), s["step_ms"]["median"], s["step_ms"]["p99"], s["fps"], s["step_cpu_ms"]["median"],
                  s["fps_cpu"], s["measurements"], s["matched"], s["active"]] for s in scaling]))
    return scaling


def profile_section(flight, plan: Plan, with_cprofile: bool) -> dict:
    """Where the time goes (wall and this thread's CPU time), and the dense matching against the batched candidate pairs."""
    print("\n== Where the time goes (timers around the functions a step calls; mean CPU ms per frame) ==")
    # CPU time of this thread: the shares do not depend on what other processes take from the core
    profiles = {n: mapper_bench.section_profile(flight, n, plan.profile_frames, clock=time.thread_time) for n in (50, 300)}
    rows = []
    for label in profiles[50]["sections_ms"]:
        rows.append([label] + sum(([profiles[n]["sections_ms"].get(label, 0.0),
                                    100 * profiles[n]["sections_ms"].get(label, 0.0) / profiles[n]["step_ms_mean"]]
                                   for n in (50, 300)), []))
    rows.sort(key=lambda r: -r[3])
    rows.append(["whole step (with timers)", profiles[50]["step_ms_mean"], 100.0, profiles[300]["step_ms_mean"], 100.0])
    print(table(["section", "ms @50", "% @50", "ms @300", "% @300"], rows))
    for n, p in profiles.items():
        if p["not_found"]:
            print(f"  (not timed at {n}: {', '.join(p['not_found'])} - renamed in the mapper?)")
    prop = {n: mapper_bench.matching_comparison(flight, n, 40 if plan.quick else 150) for n in (50, 300)}
    print("\nmatching (eqs. 10-12 and the exclusion test): dense N x M matrices against the "
          "candidate pairs the mapper now uses, same inputs, interleaved:")
    print(table(["features", "dense median ms", "dense p99", "pairs median ms", "pairs p99", "saved ms", "speedup",
                 "same decisions"],
                [[str(n), c["dense_ms"]["median"], c["dense_ms"]["p99"], c["pairs_ms"]["median"],
                  c["pairs_ms"]["p99"], c["saved_ms_median"], c["speedup"], c["identical_decisions"]]
                 for n, c in prop.items()]))
    if with_cprofile:
        for n in (50, 300):
            print(f"\ncProfile, {n} features, {plan.profile_frames} frames:")
            print(mapper_bench.cprofile_top(flight, n, plan.profile_frames))
    return {"sections": profiles, "matching_dense_vs_pairs": prop}


def loop_section(flight, plan: Plan) -> dict:
    print("\n== Batched mapper against the per-feature loop reference (same inputs, interleaved) ==")
    mu = {n: mapper_bench.compare_match_update(flight, n, f, repeats=1) for n, f in plan.match_update_frames.items()}
    whole = {n: mapper_bench.compare_whole_step(flight, n, f) for n, f in plan.whole_step_frames.items()}
    rows = []
    for n, c in mu.items():
        rows.append([f"match+update, {n} features", c["batched_ms"]["median"], c["batched_ms"]["p99"],
                     c["loop_ms"]["median"], c["loop_ms"]["p99"], c["speedup"], c["identical_decisions"]])
    for n, c in whole.items():
        rows.append([f"whole step, {n} features", c["batched_step_ms"]["median"], c["batched_step_ms"]["p99"],
                     c["loop_step_ms"]["median"], c["loop_step_ms"]["p99"], c["speedup"], "-"])
    print(table(["part", "batched med", "batched p99", "loop med", "loop p99", "speedup", "same decisions"], rows))
    print(f"  (stored features {fmt(mu[50]['features_mean'])} / {fmt(mu[300]['features_mean'])}, measurements "
          f"{fmt(mu[50]['measurements_mean'])} / {fmt(mu[300]['measurements_mean'])} per frame; largest state "
          f"difference {mu[300]['max_abs_state_difference']:.1e})")
    return {"match_update": mu, "whole_step": whole}


def map_section(flight, plan: Plan) -> dict:
    print("\n== Terrain map (1 m cells) ==")
    ins = map_bench.insert_benchmark(map_bench.converged_points(flight, 1000), plan.insert_repeats)
    av = map_bench.avoidance_benchmark(plan.query_repeats)
    print(table(["operation", "median ms", "p99 ms", "note"], [
        ["insert 1,000 converged points, mapped area", ins["mapped_area_ms"]["median"], ins["mapped_area_ms"]["p99"],
         f"{ins['pairs_cells_touched']} cells touched, {ins['tiles']} tiles"],
        ["insert 1,000 converged points, empty grid", ins["empty_grid_ms"]["median"], ins["empty_grid_ms"]["p99"],
         "tiles created"],
        ["avoidance query, 100 m look-ahead", av["query_ms"]["median"], av["query_ms"]["p99"],
         f"{av['corridor_cells']} corridor cells, engaged {av['engaged_cases']}"],
    ]))
    mem = map_bench.memory_table(list(plan.memory_shapes_m))
    print("\nmemory against map area (one point per cell; 'held' includes the tile pool's growth slack):")
    print(table(["area (m)", "km2", "tiles", "MB held", "MB/km2", "MB in tiles/km2"],
                [[m["shape_m"], m["observed_km2"], str(m["tiles"]), m["memory_MB"], m["MB_per_km2"],
                  m["tiles_MB_per_km2"]] for m in mem]))
    vs = map_bench.mapper_vs_map_size(flight, list(plan.map_sides_m), plan.map_size_frames)
    print("\nmapper per-frame cost against map size (50 features; step + depth prior + insert; interleaved):")
    print(table(["map side (m)", "km2", "tiles", "step median ms", "step p99 ms", "ray_range ms", "avoid query ms"],
                [[fmt(v["map_side_m"]), v["map_km2"], str(v["tiles"]), v["step_ms"]["median"], v["step_ms"]["p99"],
                  v["ray_range_ms"], v["avoidance_query_ms"]] for v in vs]))
    return {"insert": ins, "avoidance": av, "memory": mem, "mapper_vs_map_size": vs}


def daemon_section(plan: Plan, args) -> dict:
    if args.no_daemon:
        return {"error": "skipped (--no-daemon)"}
    common.unpin()
    seconds = args.daemon_seconds or plan.daemon_seconds
    print(f"\n== Daemon mapping at 30 fps (companion sim + companion run, {seconds:g} s after take-off; "
          "daemon on core 1, simulator on core 0) ==")
    runs = max(1, args.daemon_runs or plan.daemon_runs)
    print("  camera: the simulator renders it at each exposure and streams it over TCP (companion sim --camera-listen)")
    out = {"runs": []}
    for k in range(runs):
        if runs > 1:
            print(f"\n  run {k + 1} of {runs}:")
        out["runs"].append(daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, camera="stream"))
        _print_daemon(out["runs"][-1])
    out["default"] = median_run(out["runs"])
    if runs > 1:
        print("\n  p99 of each run: frame -> setpoint " + ", ".join(fmt(_p99(r, "frame_to_setpoint_ms")) for r in out["runs"])
              + " ms; jitter " + ", ".join(fmt(_p99(r, "jitter_ms")) for r in out["runs"]) + " ms (headline: the medians)")
    print("\n  again without the dense flow's thread (mapper.flow_rises: false), for what it costs the loop:")
    out["without_flow"] = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, camera="stream", flow=False)
    _print_daemon(out["without_flow"])
    print("\n  again with the camera rendered in the daemon's own process from SIM_STATE (camera.source: synthetic):")
    out["synthetic_camera"] = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, camera="synthetic")
    _print_daemon(out["synthetic_camera"])
    if args.daemon_experiments:
        print("\n  again with the control loop at normal scheduling (control.realtime_priority: 0):")
        out["normal_scheduling"] = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, realtime_priority=0)
        _print_daemon(out["normal_scheduling"])
        print("\n  again with the mapper in a child process (companion/service/mapper_process.py):")
        out["mapper_process"] = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, mapper_process=True)
        _print_daemon(out["mapper_process"])
        print("\n  again with Python's default GIL switch interval, 5 ms (control.gil_switch_interval_ms: 0):")
        out["switch_interval_5ms"] = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, switch_interval_s=0.0)
        _print_daemon(out["switch_interval_5ms"])
    return out


def _p99(run: dict, key: str):
    return ((run or {}).get(key) or {}).get("p99")


def median_run(runs: list[dict]) -> dict:
    """The daemon figures of repeated runs: the run whose frame -> setpoint p99 is the median (its
    details are the ones shown), with ``jitter_ms.p99`` and ``frame_to_setpoint_ms.p99`` replaced by
    the medians over the runs that completed (``p99_of_runs`` keeps them all)."""
    ok = [r for r in runs if not r.get("error") and _p99(r, "frame_to_setpoint_ms") is not None]
    if not ok:
        return runs[0] if runs else {"error": "no daemon run"}
    ok.sort(key=lambda r: _p99(r, "frame_to_setpoint_ms"))
    mid = dict(ok[len(ok) // 2])
    for key in ("frame_to_setpoint_ms", "jitter_ms"):
        values = sorted(v for v in (_p99(r, key) for r in ok) if v is not None)
        mid[key] = dict(mid.get(key) or {}, p99=float(statistics.median(values)), p99_of_runs=values)
    mid["runs_completed"] = len(ok)
    return mid


def headline_values(details: dict) -> tuple[dict, dict]:
    """The target keys (``TARGETS``) and the supporting figures, from the sections' results."""
    m, loop, mp = details["mapper"], details["batched_vs_loop"], details["map"]
    daemon = details["daemon"].get("default", details["daemon"])
    steady = daemon.get("steady_state") or {}

    def get(d, *keys):
        for k in keys:
            d = (d or {}).get(k)
        return d

    values = {
        "mapper_fps_50": m["50"]["fps"],
        "mapper_fps_300": m["300"]["fps"],
        "floor_ratio": m["50"]["floor_ratio"],
        "frame_to_setpoint_p99_ms": get(daemon, "frame_to_setpoint_ms", "p99"),
        "control_jitter_p99_ms": get(daemon, "jitter_ms", "p99"),
        "grid_insert_1000_ms": mp["insert"]["mapped_area_ms"]["median"],
        "avoidance_query_ms": mp["avoidance"]["query_ms"]["median"],
        "batched_vs_loop_speedup": loop["match_update"][50]["speedup"],
    }
    extra = {
        "mapper_fps_50_cpu": m["50"]["fps_cpu"],
        "mapper_fps_300_cpu": m["300"]["fps_cpu"],
        "floor_ratio_cpu": m["50"]["floor_ratio_cpu"],
        "floor_ratio_without_map": m[NO_MAP]["floor_ratio"],
        "mapper_fps_50_without_map": m[NO_MAP]["fps"],
        "flow_ms_per_frame": details["flow"]["mean_per_frame_ms"],
        "flow_ms_measured_frame": details["flow"]["measured_ms"]["median"],
        "flow_to_mapper_ratio": details["flow"]["ratio_to_mapper"],
        "mapper_step_ms_50": m["50"]["step_ms"],
        "mapper_step_ms_300": m["300"]["step_ms"],
        "frame_to_setpoint_p99_ms_without_flow": get(details["daemon"].get("without_flow"), "frame_to_setpoint_ms", "p99"),
        "control_jitter_p99_ms_without_flow": get(details["daemon"].get("without_flow"), "jitter_ms", "p99"),
        "frame_to_setpoint_p99_ms_synthetic_camera": get(details["daemon"].get("synthetic_camera"), "frame_to_setpoint_ms", "p99"),
        "control_jitter_p99_ms_synthetic_camera": get(details["daemon"].get("synthetic_camera"), "jitter_ms", "p99"),
        "frame_to_setpoint_p99_ms_steady": get(steady, "frame_to_setpoint_ms", "p99"),
        "queue_to_setpoint_p99_ms_steady": get(steady, "queue_to_setpoint_ms", "p99"),
        "control_jitter_p99_ms_steady": get(steady, "jitter_ms", "p99"),
        "grid_insert_1000_empty_ms": mp["insert"]["empty_grid_ms"]["median"],
        "batched_vs_loop_speedup_300": loop["match_update"][300]["speedup"],
        "batched_vs_loop_whole_step_speedup_50": loop["whole_step"][50]["speedup"],
        "memory_MB_per_km2_square": next(r["MB_per_km2"] for r in mp["memory"] if r["shape_m"] == "1000 x 1000"),
        "memory_MB_per_km2_strip": next(r["MB_per_km2"] for r in mp["memory"] if r["shape_m"] == "10000 x 100"),
    }
    return values, extra


def print_targets(values: dict, extra: dict) -> None:
    print("\n== Targets ==")
    rows = []
    for key, (target, kind, unit, what) in TARGETS.items():
        v = values[key]
        met = None if v is None or target is None else (v >= target if kind == "min" else v <= target)
        rows.append([key, fmt(v), "-" if target is None else f"{'>=' if kind == 'min' else '<='} {target:g} {unit}",
                     {True: "met", False: "MISSED", None: "-"}[met], what])
    print(table(["key", "measured", "target", "", "what"], rows))
    print(f"memory per km2 observed at 1 m cells: {fmt(extra['memory_MB_per_km2_square'])} MB (1 km square), "
          f"{fmt(extra['memory_MB_per_km2_strip'])} MB (10 km x 100 m strip)")
    print(f"without the dense flow's thread: frame -> setpoint p99 {fmt(extra['frame_to_setpoint_p99_ms_without_flow'])} ms, "
          f"jitter p99 {fmt(extra['control_jitter_p99_ms_without_flow'])} ms (the headline flies with it, on the daemon's one core)")
    print(f"with the camera rendered in the daemon's process instead (synthetic): frame -> setpoint p99 "
          f"{fmt(extra['frame_to_setpoint_p99_ms_synthetic_camera'])} ms, jitter p99 "
          f"{fmt(extra['control_jitter_p99_ms_synthetic_camera'])} ms")
    print(f"steady state (from 5 s after take-off): frame -> setpoint p99 {fmt(extra['frame_to_setpoint_p99_ms_steady'])} ms "
          f"(daemon's own part, queue -> setpoint: {fmt(extra['queue_to_setpoint_p99_ms_steady'])} ms), "
          f"jitter p99 {fmt(extra['control_jitter_p99_ms_steady'])} ms; CPU-time frames/s "
          f"{fmt(extra['mapper_fps_50_cpu'])} @50, {fmt(extra['mapper_fps_300_cpu'])} @300")


def _public(d: dict) -> dict:
    return {k: v for k, v in d.items() if not k.startswith("_")}


def _print_daemon(d: dict) -> None:
    if d.get("error"):
        print(f"  daemon run failed: {d['error']}")
        tail = d.get("daemon_log_tail")
        if tail:
            print("  daemon log (end):\n" + "\n".join("    " + line for line in tail.splitlines()[-15:]))
        return
    rows = []
    for name, key in (("frame -> setpoint", "frame_to_setpoint_ms"), ("control jitter (20 Hz)", "jitter_ms"),
                      ("mapper step in the daemon", "mapper_step_ms")):
        s = d.get(key) or {}
        rows.append([name, str(s.get("n")), s.get("p50"), s.get("p99"), s.get("max")])
    print(table(["figure (daemon status, whole run)", "n", "p50 ms", "p99 ms", "max ms"], rows))
    ss = d.get("steady_state") or {}
    if ss.get("jitter_ms"):
        parts = ss.get("parts_ms", {})
        rows = []
        for name, v in (("frame -> setpoint", ss.get("frame_to_setpoint_ms")),
                        ("  of which queue -> setpoint (daemon's own)", ss.get("queue_to_setpoint_ms")),
                        ("  frame stamp -> queue (sim pose age + render)", parts.get("capture_to_queue")),
                        ("  render (synthetic camera, in the daemon)", parts.get("render_in_daemon")),
                        ("  queue wait", parts.get("queue_wait")),
                        ("  mapper step + grid insert", parts.get("map_step_and_insert")),
                        ("control jitter (20 Hz)", ss.get("jitter_ms"))):
            v = v or {}
            rows.append([name, str(v.get("n")), v.get("median"), v.get("p99"), v.get("mean")])
        print(f"  steady state (samples from {ss.get('from_s_after_takeoff'):g} s after take-off, the daemon's own samples):")
        print(table(["figure", "n", "median ms", "p99 ms", "mean ms"], rows))
        lt = ss.get("late_ticks") or {}
        if lt.get("during_mapper_step") is not None:
            print(f"  control ticks later than {lt['threshold_ms']:g} ms: {lt['n']}, of which {lt['during_mapper_step']} "
                  f"while the mapper thread was stepping (chance alone: {100 * lt['chance_fraction']:.0f} %)")
    print(f"  frames {d.get('frames_in')} in, {d.get('frames_mapped')} mapped, {d.get('queue_dropped')} dropped by the "
          f"queue; {d.get('points_converged')} points converged; command state: {d.get('command')}")
    fl = d.get("flow_status") or {}
    if fl.get("on"):
        step, to_map = fl.get("step_ms") or {}, fl.get("frame_to_map_ms") or {}
        print(f"  dense flow (its own thread, nice {fl.get('thread_nice')}): {fl.get('frames_measured')} frames measured, "
              f"{fl.get('queue_dropped')} dropped by its queue, {fl.get('floors')} floors; step p50 / p99 "
              f"{fmt(step.get('p50'))} / {fmt(step.get('p99'))} ms, capture -> floors in the map p50 / p99 "
              f"{fmt(to_map.get('p50'))} / {fmt(to_map.get('p99'))} ms")
    rt = d.get("realtime")
    print("  control loop thread: " + ("normal scheduling (control.realtime_priority: 0)" if not rt else
          f"SCHED_FIFO priority {rt['priority']}" if rt.get("active") else f"normal scheduling ({rt.get('reason')})"))


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


if __name__ == "__main__":
    sys.exit(main())
