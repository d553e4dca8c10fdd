"""``companion quality --shared-first-pass N``: what another vehicle's map buys on the first pass
(docs/terrain.md, "Evidence from other vehicles"; docs/quality.md).

For each scenario and seed: a *scout* (the seed + 1000: its own navigation errors, wind and camera
noise) flies ``N`` laps; then the vehicle flies its first lap twice, alone and with the scout's map
in the view its law reads (:class:`companion.method.terrain.sharing.SharedView`). Both fly from the
simulator's one EKF origin, so the scout's map is placed at a zero offset, and the two maps
disagree by their navigation errors as two vehicles' do. Reported per obstacle: the first-pass
clearance (fraction of the configured clearance) alone and shared, and the height the scout's map
holds over it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

SCOUT_SEED_OFFSET = 1000


def fly_pair(job: tuple[str, int, int, tuple]) -> dict[str, Any]:
    """One (scenario, seed, scout laps, overrides): the figures above. Never raises: a failure is a
    row with ``problem`` set."""
    scenario, seed, scout_laps, overrides = job
    t0 = time.perf_counter()
    try:
        from companion.desk.quality import engine, metrics
        from companion.desk.quality.scenarios import flight_config
        from companion.desk.quality.suite import CAMERA_RATE_HZ
        from companion.method.terrain.sharing import SharedEvidence, SharedView
        from drivers.sim.world import World

        world = World.load(scenario)
        scout_cfg = flight_config(world, scenario, "inverse_depth", seed + SCOUT_SEED_OFFSET, CAMERA_RATE_HZ, overrides)
        grids = []
        scout = engine.fly(scenario, scout_cfg, scout_laps, world=world,
                           on_frame=lambda *a: grids.append(a[-1]) if not grids else None)
        if not grids:
            raise RuntimeError(f"the scout mapped nothing ({scout.problem or 'no frame'})")
        grid = grids[0]
        shared = SharedEvidence("vehicle", grid.cell_size_m, grid.tile_cells)
        shared.set_frame("scout", (0.0, 0.0, grid.frame_shift_m))  # as published: the map's frame, its offset
        for key in grid.keys():
            shared.put("scout", grid.tile(key, in_map_frame=True))
        cfg = flight_config(world, scenario, "inverse_depth", seed, CAMERA_RATE_HZ, overrides)
        alone = metrics.run_figures(engine.fly(scenario, cfg, 1, world=world), world)
        with_scout = metrics.run_figures(engine.fly(scenario, cfg, 1, world=world,
                                                    law_view=lambda g: SharedView(g, shared, cfg.terrain.gate_sigma)), world)
        scout_map = metrics.run_figures(scout, world)["map"]["obstacles"]
        rows = []
        for a, s in zip(_obstacles(alone), _obstacles(with_scout)):
            rows.append({"obstacle": a["name"], "alone": a.get("min_clearance_fraction"), "shared": s.get("min_clearance_fraction"),
                         "scout_mapped_height_m": (scout_map.get(a["name"]) or {}).get("mapped_height_m"),
                         "height_m": (scout_map.get(a["name"]) or {}).get("height_m")})
        return {"scenario": scenario, "seed": seed, "scout_laps": scout_laps, "obstacles": rows, "problem": "",
                "wall_s": round(time.perf_counter() - t0, 1)}
    except Exception as exc:  # noqa: BLE001 - reported as a failed row
        return {"scenario": scenario, "seed": seed, "scout_laps": scout_laps, "obstacles": [],
                "problem": f"{type(exc).__name__}: {exc}", "wall_s": round(time.perf_counter() - t0, 1)}


def _obstacles(run: dict) -> list[dict]:
    laps = run.get("laps") or []
    return list(laps[0].get("obstacles") or []) if laps else []


def markdown(results: list[dict], command: str) -> str:
    def f(x, d=2):
        return "-" if x is None else f"{x:.{d}f}"

    lines = ["# What another vehicle's map buys on the first pass", "",
             f"`{command}`: a scout flies first, then each vehicle flies its first lap alone and with the scout's map "
             "(companion/desk/quality/fleet.py, docs/terrain.md \"Evidence from other vehicles\"). First-pass clearance as a "
             "fraction of the configured clearance; the scout's mapped height over the obstacle against its true height.", "",
             "| scenario | seed | obstacle | alone | with the scout's map | scout's map holds (m) |",
             "|---|---:|---|---:|---:|---:|"]
    for r in results:
        if r["problem"]:
            lines.append(f"| {r['scenario']} | {r['seed']} | failed: {r['problem']} | | | |")
        for o in r["obstacles"]:
            lines.append(f"| {r['scenario']} | {r['seed']} | {o['obstacle']} | {f(o['alone'])} | {f(o['shared'])} | "
                         f"{f(o['scout_mapped_height_m'], 1)} of {f(o['height_m'], 1)} |")
    return "\n".join(lines) + "\n"


def run(scenarios: list[str], seeds: list[int], scout_laps: int, overrides: tuple, jobs: int, out: Path, command: str) -> int:
    """Fly every pair (in ``jobs`` processes), write ``shared.json`` and ``shared.md``; exit status."""
    import concurrent.futures
    import multiprocessing

    work = [(s, seed, scout_laps, overrides) for s in scenarios for seed in seeds]
    if jobs > 1 and len(work) > 1:
        with concurrent.futures.ProcessPoolExecutor(min(jobs, len(work)), mp_context=multiprocessing.get_context("spawn")) as pool:
            results = list(pool.map(fly_pair, work))
    else:
        results = [fly_pair(job) for job in work]
    out.mkdir(parents=True, exist_ok=True)
    (out / "shared.json").write_text(json.dumps({"command": command, "results": results}, indent=1))
    (out / "shared.md").write_text(markdown(results, command))
    print(markdown(results, command))
    return 0 if results and not any(r["problem"] for r in results) else 1
