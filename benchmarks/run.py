"""``python -m benchmarks.run [--quick]``: every figure of issue 7 in one run.

Prints tables (median and p99 over repeated runs, the machine) and writes
``benchmarks/results.json``. Single-core figures run pinned to core 0 with OpenCV single-threaded;
the daemon run gives the daemon core 1 and the simulator core 0. Nothing here asserts: a target
that is missed is printed as missed. See docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from benchmarks import common
from benchmarks.common import fmt, table

RESULTS = Path(__file__).resolve().parent / "results.json"

# key -> (target, "min" = at least / "max" = at most, unit, what)
TARGETS = {
    "mapper_fps_50": (250.0, "min", "frames/s", "mapper step, 640x480, 50 features, one core"),
    "mapper_fps_300": (100.0, "min", "frames/s", "mapper step, 640x480, 300 features, one core"),
    "floor_ratio": (2.5, "max", "x", "mapper step / cv2.cornerHarris alone, same frames (50 features)"),
    "frame_to_setpoint_p99_ms": (15.0, "max", "ms", "daemon mapping at 30 fps: frame stamp -> setpoint, p99"),
    "control_jitter_p99_ms": (5.0, "max", "ms", "daemon control loop at 20 Hz: lateness of the tick, p99"),
    "grid_insert_1000_ms": (1.0, "max", "ms", "TerrainGrid.insert of 1,000 converged points (median, mapped area)"),
    "avoidance_query_ms": (0.5, "max", "ms", "PullUpLaw.command, 100 m look-ahead over a mapped area (median)"),
    "batched_vs_loop_speedup": (None, "min", "x", "match+update, batched vs per-feature loop, 50 features (median)"),
}


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="short run (under a minute): fewer frames and repeats")
    p.add_argument("--out", default=str(RESULTS), help="results file (default benchmarks/results.json)")
    p.add_argument("--no-daemon", action="store_true", help="skip the daemon run (simulator + companion run)")
    p.add_argument("--daemon-seconds", type=float, help="daemon run length after take-off (default 40, quick 12)")
    p.add_argument("--gil-experiment", action="store_true",
                   help="also run the daemon with sys.setswitchinterval(0.001) (evidence for a proposal)")
    p.add_argument("--profile", action="store_true", help="also print cProfile's top functions of the mapper step")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    from benchmarks import daemon_bench, map_bench, mapper_bench

    quick = args.quick
    # frames rendered; repeats of the headline run; frames for the scaling, profile, comparisons
    n_frames = 90 if quick else 600
    repeats = 1 if quick else 2
    scale_frames = 60 if quick else 300
    profile_frames = 60 if quick else 200
    feature_counts = [10, 50, 100, 300, 500] if quick else [10, 25, 50, 100, 200, 300, 400, 500]
    t_start = time.perf_counter()
    pinned = common.pin_one_core(0)
    machine = common.machine_info()
    print(f"companion benchmarks ({'quick' if quick else 'full'}): {machine['cpu']}, {machine['cpus']} CPUs, "
          f"Python {machine['python']}, NumPy {machine['numpy']}, OpenCV {machine['opencv']}")
    print(f"single-core figures on core 0 (pinned: {pinned}), cv2 threads {machine['opencv_threads']}, "
          f"load average {machine['loadavg']}")
    details: dict = {}
    timings: dict[str, float] = {}
    last = [time.perf_counter()]

    def section(name: str) -> None:
        now = time.perf_counter()
        timings[name] = round(now - last[0], 1)
        last[0] = now

    # -- the flight --------------------------------------------------------------------------
    t0 = time.perf_counter()
    flight = common.render_flight(n_frames)
    r = common.summary(flight.render_ms)
    print(f"\nrendered {len(flight)} frames 640x480 at {common.RATE_HZ:g} Hz along the default circuit "
          f"(north {common.START_NORTH_M:g} -> {common.START_NORTH_M + common.SPEED_MPS * n_frames / common.RATE_HZ:.0f} m) "
          f"in {time.perf_counter() - t0:.1f} s (render median {fmt(r['median'])} ms)")
    details["flight"] = {"frames": len(flight), "rate_hz": common.RATE_HZ, "render_ms": r}

    section("flight")

    # -- mapper throughput and the floor -----------------------------------------------------
    print("\n== Mapper step (detect + match + update + initialise), one core ==")
    headline = mapper_bench.run_interleaved(flight, {n: mapper_bench.variant(flight, n) for n in (50, 300)},
                                            repeats=repeats, with_floor=True)
    for n, h in headline.items():
        h["n_features"] = n
    rows = []
    for n, h in headline.items():
        rows.append([str(n), h["step_ms"]["median"], h["step_ms"]["p99"], h["fps"], 1e3 / h["step_ms"]["median"],
                     h["measurements"], h["matched"], h["active"], h["points_per_frame"]])
    print(table(["features", "median ms", "p99 ms", "frames/s", "1/median", "meas/frame", "matched", "stored",
                 "points out"], rows))
    h50 = headline[50]
    print(f"floor: cv2.cornerHarris alone median {fmt(h50['harris_ms']['median'])} ms (p99 {fmt(h50['harris_ms']['p99'])}); "
          f"step / Harris = {fmt(h50['floor_ratio'])} (median of per-frame ratios {fmt(h50['floor_ratio_per_frame_median'])})")
    details["mapper"] = {str(n): {k: v for k, v in h.items() if not k.startswith("_")} for n, h in headline.items()}

    section("mapper throughput")

    # -- scaling with N ----------------------------------------------------------------------
    print(f"\n== Time per frame against the number of features ({scale_frames} frames, one pass each) ==")
    runs = mapper_bench.run_interleaved(flight, {n: mapper_bench.variant(flight, n) for n in feature_counts},
                                        repeats=1, frames=scale_frames)
    scaling = []
    for n, s in runs.items():
        scaling.append({"n_features": n, **{k: v for k, v in s.items() if not k.startswith("_")}})
    print(table(["features", "median ms", "p99 ms", "frames/s", "meas/frame", "matched", "stored"],
                [[str(s["n_features"]), s["step_ms"]["median"], s["step_ms"]["p99"], s["fps"], s["measurements"],
                  s["matched"], s["active"]] for s in scaling]))
    details["scaling_features"] = scaling

    section("scaling")

    # -- where the time goes -----------------------------------------------------------------
    print("\n== Where the time goes (timers around the functions a step calls; mean ms per frame) ==")
    profiles = {n: mapper_bench.section_profile(flight, n, profile_frames) for n in (50, 300)}
    labels = list(profiles[50]["sections_ms"])
    prow = []
    for label in labels:
        prow.append([label] + sum(([profiles[n]["sections_ms"].get(label, 0.0),
                                    100 * profiles[n]["sections_ms"].get(label, 0.0) / profiles[n]["step_ms_mean"]]
                                   for n in (50, 300)), []))
    prow.sort(key=lambda r: -r[3])
    prow.append(["whole step (with timers)", profiles[50]["step_ms_mean"], 100.0, profiles[300]["step_ms_mean"], 100.0])
    print(table(["section", "ms @50", "% @50", "ms @300", "% @300"], prow))
    for n, p in profiles.items():
        if p["not_found"]:
            print(f"  (not timed at {n}: {', '.join(p['not_found'])} - renamed in the mapper?)")
    details["profile_sections"] = profiles
    prop = {n: mapper_bench.distance_proposal(flight, n, 40 if quick else 150) for n in (50, 300)}
    print("\nproposal 1 measured: N x M distances + exclusion as now (einsum, (N, M, 2) temporaries) against the "
          "same maths by components (benchmarks/mapper_bench.py:distances_by_components), same inputs:")
    print(table(["features", "now median ms", "now p99", "by components med", "p99", "saved ms", "speedup", "max rel diff"],
                [[str(n), c["current_ms"]["median"], c["current_ms"]["p99"], c["prototype_ms"]["median"],
                  c["prototype_ms"]["p99"], c["saved_ms_median"], c["speedup"], f"{c['max_relative_difference']:.1e}"]
                 for n, c in prop.items()]))
    details["proposal_distances"] = prop
    if args.profile:
        for n in (50, 300):
            print(f"\ncProfile, {n} features, {profile_frames} frames:")
            print(mapper_bench.cprofile_top(flight, n, profile_frames))

    section("profile")

    # -- batched against the loop reference --------------------------------------------------
    print("\n== Batched mapper against the per-feature loop reference (same inputs) ==")
    comp_frames = {50: 60, 300: 30} if quick else {50: 300, 300: 120}
    whole_frames = {50: 40} if quick else {50: 150, 300: 60}
    mu = {n: mapper_bench.compare_match_update(flight, n, comp_frames[n], repeats=1) for n in (50, 300)}
    whole = {n: mapper_bench.compare_whole_step(flight, n, f) for n, f in whole_frames.items()}
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
    details["batched_vs_loop"] = {"match_update": mu, "whole_step": whole}

    section("batched vs loop")

    # -- the map -----------------------------------------------------------------------------
    print("\n== Terrain map (1 m cells) ==")
    pts = map_bench.converged_points(flight, 1000)
    ins = map_bench.insert_benchmark(pts, 30 if quick else 200)
    av = map_bench.avoidance_benchmark(100 if quick else 500)
    print(table(["operation", "median ms", "p99 ms", "note"], [
        ["insert 1,000 converged points, mapped area", ins["mapped_area_ms"]["median"], ins["mapped_area_ms"]["p99"],
         f"{ins['pairs_cells_touched']} cells touched, {ins['tiles']} tiles"],
        ["insert 1,000 converged points, empty grid", ins["empty_grid_ms"]["median"], ins["empty_grid_ms"]["p99"],
         "tiles created"],
        ["avoidance query, 100 m look-ahead", av["query_ms"]["median"], av["query_ms"]["p99"],
         f"{av['corridor_cells']} corridor cells, engaged {av['engaged_cases']}"],
    ]))
    shapes = [(100, 100), (316, 316), (1000, 1000), (10000, 100)] if not quick else [(100, 100), (1000, 1000), (10000, 100)]
    mem = map_bench.memory_table([(float(a), float(b)) for a, b in shapes])
    print("\nmemory against map area (one point per cell):")
    print(table(["area (m)", "km2", "tiles", "MB held", "MB/km2", "MB in tiles/km2"],
                [[m["shape_m"], m["observed_km2"], str(m["tiles"]), m["memory_MB"], m["MB_per_km2"],
                  m["tiles_MB_per_km2"]] for m in mem]))
    sides = [0.0, 1000.0] if quick else [0.0, 300.0, 1000.0, 2000.0]
    vs = map_bench.mapper_vs_map_size(flight, sides, 40 if quick else 150)
    print("\nmapper per-frame cost against map size (50 features; step + depth prior + insert):")
    print(table(["map side (m)", "km2", "tiles", "step median ms", "step p99 ms", "ray_range ms", "avoid query ms"],
                [[fmt(v["map_side_m"]), v["map_km2"], str(v["tiles"]), v["step_ms"]["median"], v["step_ms"]["p99"],
                  v["ray_range_ms"], v["avoidance_query_ms"]] for v in vs]))
    details["map"] = {"insert": ins, "avoidance": av, "memory": mem, "mapper_vs_map_size": vs}

    section("map")

    # -- the daemon --------------------------------------------------------------------------
    daemon = {"error": "skipped (--no-daemon)"}
    gil = None
    if not args.no_daemon:
        common.unpin()
        seconds = args.daemon_seconds or (8.0 if quick else 40.0)
        print(f"\n== Daemon mapping at 30 fps (companion sim + companion run, {seconds:g} s after take-off; "
              "daemon on core 1, simulator on core 0) ==")
        daemon = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print)
        _print_daemon(daemon)
        if args.gil_experiment:
            print("\n  again with the daemon's GIL switch interval at 1 ms (sys.setswitchinterval(0.001)):")
            gil = daemon_bench.run_daemon_benchmark(seconds, 30.0, log=print, switch_interval_s=0.001)
            _print_daemon(gil)
    details["daemon"] = daemon
    if gil is not None:
        details["daemon_switch_interval_1ms"] = gil

    section("daemon")

    # -- results -----------------------------------------------------------------------------
    def p99(d, key):
        v = (d or {}).get(key) or {}
        return v.get("p99")

    values = {
        "mapper_fps_50": headline[50]["fps"],
        "mapper_fps_300": headline[300]["fps"],
        "floor_ratio": h50["floor_ratio"],
        "frame_to_setpoint_p99_ms": p99(daemon, "frame_to_setpoint_ms"),
        "control_jitter_p99_ms": p99(daemon, "jitter_ms"),
        "grid_insert_1000_ms": ins["mapped_area_ms"]["median"],
        "avoidance_query_ms": av["query_ms"]["median"],
        "batched_vs_loop_speedup": mu[50]["speedup"],
    }
    extra = {
        "grid_insert_1000_empty_ms": ins["empty_grid_ms"]["median"],
        "batched_vs_loop_speedup_300": mu[300]["speedup"],
        "batched_vs_loop_whole_step_speedup_50": whole[50]["speedup"],
        "memory_MB_per_km2_square": next(m["MB_per_km2"] for m in mem if m["shape_m"] == "1000 x 1000"),
        "memory_MB_per_km2_strip": next(m["MB_per_km2"] for m in mem if m["shape_m"] == "10000 x 100"),
        "frame_to_setpoint_p99_ms_steady": ((daemon.get("steady_state") or {}).get("frame_to_setpoint_ms") or {}).get("p99"),
        "queue_to_setpoint_p99_ms_steady": ((daemon.get("steady_state") or {}).get("queue_to_setpoint_ms") or {}).get("p99"),
        "control_jitter_p99_ms_steady": ((daemon.get("steady_state") or {}).get("jitter_ms") or {}).get("p99"),
        "mapper_step_ms_50": headline[50]["step_ms"],
        "mapper_step_ms_300": headline[300]["step_ms"],
    }
    print("\n== Targets ==")
    trows = []
    for key, (target, kind, unit, what) in TARGETS.items():
        v = values[key]
        met = None if v is None or target is None else (v >= target if kind == "min" else v <= target)
        trows.append([key, fmt(v), "-" if target is None else f"{'>=' if kind == 'min' else '<='} {target:g} {unit}",
                      {True: "met", False: "MISSED", None: "-"}[met], what])
    print(table(["key", "measured", "target", "", "what"], trows))
    print(f"memory per km2 observed at 1 m cells: {fmt(extra['memory_MB_per_km2_square'])} MB (1 km square), "
          f"{fmt(extra['memory_MB_per_km2_strip'])} MB (10 km x 100 m strip)")
    out = {**values, **extra,
           "targets": {k: {"target": t, "kind": kind, "unit": u, "what": w, "measured": values[k]}
                       for k, (t, kind, u, w) in TARGETS.items()},
           "mode": "quick" if quick else "full", "machine": machine,
           "loadavg_at_end": common.machine_info()["loadavg"],
           "run_seconds": round(time.perf_counter() - t_start, 1), "section_seconds": timings,
           "generated_unix_s": round(time.time(), 1), "details": details}
    Path(args.out).write_text(json.dumps(out, indent=1, default=_json_default))
    print(f"\nwrote {args.out} ({out['run_seconds']:.0f} s: " + ", ".join(f"{k} {v:g}" for k, v in timings.items()) + ")")
    return 0


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
    print(f"  frames {d.get('frames_in')} in, {d.get('frames_mapped')} mapped, {d.get('queue_dropped')} dropped by the "
          f"queue; {d.get('points_converged')} points converged; command state: {d.get('command')}")


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


if __name__ == "__main__":
    sys.exit(main())
