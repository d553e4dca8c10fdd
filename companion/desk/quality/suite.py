"""``companion quality``: the scenario suite (docs/quality.md).

Every scenario x seed x mapper parameterisation is one flight of the service's closed loop in
simulated time (:mod:`companion.quality.engine`), judged by the pilot's figures
(:mod:`companion.quality.metrics`). Flights run in parallel, one per core; a flight that fails to
complete is reported as a failure with its reason, never dropped, and makes the exit status 1.
Writes ``quality.json`` (schema ``companion.quality/1``), ``quality.md`` and, in ``quality/``, the
side profile of each scenario's worst first pass.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import multiprocessing
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from companion.config import ConfigError

PARAMETERISATIONS = ("inverse_depth", "cartesian")
CAMERA_RATE_HZ = 15.0          # as the demo (the paper's camera ran at 16 Hz)
DEFAULT_LAPS = 3               # the first pass and two more: the paper's figures are after three laps
QUICK_SCENARIOS = ("default", "flat")
SCHEMA = "companion.quality/1"


def scenario_names() -> list[str]:
    """Every scenario in config/scenarios/, in name order."""
    from drivers.sim.world import SCENARIO_DIR

    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def parse_seeds(text: str) -> list[int]:
    """``"3"`` -> [1, 2, 3]; ``"1,5,9"`` -> [1, 5, 9]."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--seeds {text!r}: a count (3) or a comma-separated list (1,5,9) of integers") from None
    if len(values) == 1 and "," not in text:
        if not 1 <= values[0] <= 1000:
            raise ConfigError(f"--seeds {text!r}: the count must be within 1..1000")
        return list(range(1, values[0] + 1))
    if not values or any(not 0 <= v < 2**31 for v in values):
        raise ConfigError(f"--seeds {text!r}: seeds must be within 0..2^31-1")
    return values


def _overrides(args) -> tuple[tuple[str, dict], ...]:
    from companion.desk.quality.scenarios import override_layers

    return override_layers(args.config, args.set)


# --------------------------------------------------------------------------------------------
# One flight (in a worker process)
# --------------------------------------------------------------------------------------------

_WORLDS: dict[str, Any] = {}


def fly_one(job: tuple[str, int, str, int, tuple]) -> dict[str, Any]:
    """Fly one (scenario, seed, parameterisation, laps, overrides); the run's figures plus the
    first lap's side profile. Never raises: a failure is a run with ``complete`` false."""
    scenario, seed, param, laps, overrides = job
    t0 = time.perf_counter()
    try:
        from companion.desk import report
        from companion.desk.quality import engine, metrics
        from companion.desk.quality.scenarios import flight_config
        from drivers.sim.world import World

        if scenario not in _WORLDS:
            _WORLDS[scenario] = World.load(scenario)
        world = _WORLDS[scenario]
        cfg = flight_config(world, scenario, param, seed, CAMERA_RATE_HZ, overrides)
        rec = engine.fly(scenario, cfg, laps, world=world)
        run = metrics.run_figures(rec, world)
        run.update(engine.record_summary(rec))
        profile = None
        if len(rec.t_s):
            end = rec.lap_ends[0] + 1 if rec.lap_ends else len(rec.t_s)
            lap_map = rec.lap_maps[0] if rec.lap_maps else rec.final_map
            p = report.lap_profile(rec.truth_ne_m[:end], rec.truth_alt_m[:end], world.terrain_height, lap_map,
                                   corridor_m=cfg.avoidance.miss_distance_m, max_points=1500)
            profile = {k: np.asarray(getattr(p, k), float).tolist() for k in
                       ("distance_m", "alt_m", "true_terrain_m", "mapped_terrain_m", "mapped_corridor_max_m")}
        return {"run": run, "profile": profile, "description": world.spec.description}
    except Exception as exc:  # noqa: BLE001 - reported as a failed run
        return {"run": {"scenario": scenario, "seed": seed, "parameterisation": param, "complete": False,
                        "problem": f"{type(exc).__name__}: {exc}", "laps_requested": laps, "speed_flown_mps": None,
                        "laps": [], "map": {"flat": {}, "obstacles": {}, "all": {}},
                        "wall_s": round(time.perf_counter() - t0, 1)},
                "profile": None, "description": ""}


# --------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------


def _vals(runs: list[dict], get) -> list[float]:
    out = []
    for r in runs:
        try:
            v = get(r)
        except (KeyError, IndexError, TypeError):
            v = None
        if v is not None and math.isfinite(v):
            out.append(float(v))
    return out


def _lap(r: dict, k: int) -> dict:
    return r["laps"][k] if len(r.get("laps") or []) > k else {}


def summarise(runs: list[dict]) -> list[dict[str, Any]]:
    """One row per (scenario, parameterisation) over its seeds: the worst of each figure."""
    rows = []
    keys = sorted({(r["scenario"], r["parameterisation"]) for r in runs},
                  key=lambda k: (k[0], PARAMETERISATIONS.index(k[1]) if k[1] in PARAMETERISATIONS else 9))
    for scenario, param in keys:
        group = [r for r in runs if r["scenario"] == scenario and r["parameterisation"] == param]
        first = _vals(group, lambda r: _lap(r, 0).get("min_clearance_fraction"))
        every = _vals([lap for r in group for lap in r.get("laps") or []], lambda lap: lap.get("min_clearance_fraction"))
        laps_all = [lap for r in group for lap in r.get("laps") or []]
        margin = _vals(laps_all, lambda lap: None if lap.get("warning_s") is None else lap["warning_s"] - lap["needed_s"])
        # a lap whose obstacle the map never held has no warning at all: the worst there is
        never_held = any(lap.get("warning_s") is None and lap.get("needed_s") is not None for lap in laps_all)
        med = _vals([lap for r in group for lap in r.get("laps") or []], lambda lap: lap.get("cruise_excess_median_m"))
        p95 = _vals([lap for r in group for lap in r.get("laps") or []], lambda lap: lap.get("cruise_excess_p95_m"))
        eng = _vals([lap for r in group for lap in r.get("laps") or []], lambda lap: lap.get("engaged_flat_fraction"))
        false = _vals([lap for r in group for lap in r.get("laps") or []], lambda lap: lap.get("false_climbs"))
        phantoms = _vals(group, lambda r: r.get("points_in_front"))
        # judged over the obstacles the second lap flew over: one beside the route may never be in view
        obst = _vals([o for r in group for o in (_lap(r, 1).get("obstacles") or []) if o.get("reached")],
                     lambda o: o.get("mapped_fraction_of_textured"))
        rows.append({
            "scenario": scenario, "parameterisation": param, "runs": len(group),
            "complete": sum(1 for r in group if r.get("complete")),
            "first_pass_min_clearance_fraction": min(first) if first else None,
            "min_clearance_fraction": min(every) if every else None,
            "worst_warning_margin_s": None if never_held or not margin else min(margin),
            "obstacle_never_held": never_held,
            "cruise_excess_median_m": max(med) if med else None,
            "cruise_excess_p95_m": max(p95) if p95 else None,
            "engaged_flat_fraction": max(eng) if eng else None,
            "false_climbs": int(sum(false)) if false else 0,
            "phantom_points": int(sum(phantoms)) if phantoms else None,
            "flat_bias_m": _mean(_vals(group, lambda r: r["map"]["flat"].get("bias_m"))),
            "flat_within_1m": min(_vals(group, lambda r: r["map"]["flat"].get("within_1m")), default=None),
            "all_rmse_m": _mean(_vals(group, lambda r: r["map"]["all"].get("rmse_m"))),
            # The same in the navigation's frame at the map's time (metrics.map_figures, frame_m).
            "flat_bias_nav_m": _mean(_vals(group, lambda r: (r.get("map_nav_frame") or _NO_MAP)["flat"].get("bias_m"))),
            "flat_within_1m_nav": min(_vals(group, lambda r: (r.get("map_nav_frame") or _NO_MAP)["flat"].get("within_1m")),
                                      default=None),
            "all_rmse_nav_m": _mean(_vals(group, lambda r: (r.get("map_nav_frame") or _NO_MAP)["all"].get("rmse_m"))),
            "obstacle_height_lap2_fraction": min(obst) if obst else None,
            "speed_flown_mps": _mean(_vals(group, lambda r: r.get("speed_flown_mps"))),
            "speed_commanded_mps": group[0].get("speed_commanded_mps"),
        })
    return rows


_NO_MAP = {"flat": {}, "all": {}}  # a run recorded before the map was also judged in the navigation's frame


def _mean(v: list[float]) -> float | None:
    return float(np.mean(v)) if v else None


def _f(x, fmt: str = "{:.2f}") -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


DEFINITIONS = """\
## What each figure means

Every figure comes from the flight's own record; nothing is excused: every lap counts, the
first included, and every obstacle in every lap. The code is companion/desk/quality/metrics.py.

- **first-pass / least clearance fraction**: the least height of the vehicle above the true
  terrain directly below it, over the lap (first lap / any lap), divided by the configured
  clearance. Per obstacle: the same over the samples above its footprint.
- **warning margin** (s): per obstacle and lap, *warning* = the time the vehicle reached the
  obstacle's footprint minus the first time the map held it high enough to need a climb (a
  footprint cell, as the law takes it: estimate + `avoidance.height_margin_sigma` sigma, plus the
  clearance above the nominal altitude); *needed* = the law's shortest climb from the nominal
  altitude to the obstacle's height + clearance (`stopping_time`, with the law's acceleration
  and climb limit). The margin is warning - needed: negative = the map got it too late for a
  smooth climb. An obstacle never held has no warning (shown as the worst). The lap's figure is
  its worst obstacle.
- **cruise excess** (m): altitude minus the commanded height over flat ground far from
  obstacles: the true terrain below is flat, and along the path flown no sample above an
  obstacle's footprint (grown by the miss distance) lies within the law's climb distance ahead
  (miss distance + speed x shortest climb to obstacle + clearance) or its return distance behind
  (miss distance + speed x (descent at the descent limit + 3 time constants)). Median and 95th
  percentile per lap; the table gives the worst lap.
- **engaged over flat**: the fraction of those flat-ground samples where the law was engaged
  (an obstacle term demanded more than the nominal-altitude command).
- **false climbs**: engaged episodes where, at the step of the largest commanded climb, the
  limiting cell lies on flat true ground (the cell and one cell around it, as for the map's flat
  cells below, so a cell beside a face is not one) and its mapped height is more than 2 m above that ground
  in the navigation's frame of that step (the true ground plus the estimate's altitude error
  then: the map is built from the estimate's poses, so a cell holding the ground where the vehicle
  believes it is, is no false cell; the cruise excess judges that error). An unmapped limiting
  cell, standing in at the highest mapped cell within 5 m along track (docs/avoidance.md,
  "Unmapped cells"), is judged by that mapped cell; one held at its own floor or ceiling (no
  mapped cell to stand in for) by the height the law took for it.
- **phantom points**: emitted points more than 2 m and more than 5 of their own sigmas nearer the
  camera than the true surface about their line of sight (above the ground, before a face; the
  nearest of the surfaces along the line of sight and lines 0.002-0.01 rad off it, so a point on
  an obstacle's outline is not counted), summed over the seeds; each point is compared in the frame
  it was seen in, so the navigation's error is not counted (quality.json per run:
  `points_scored`, `points_in_front`, `points_behind`).
- **map, flat**: cells whose true terrain is flat over the cell and one cell around it: bias
  (mean of mapped - true), RMSE, fraction within 1 m, and coverage (of the flat cells a camera ray
  met, the fraction the map holds). **map, all**: RMSE over every mapped cell. Each cell is judged
  against the highest true terrain over it (sampled on a 5 x 5 lattice), what a cell claims (the
  fusion keeps a cell's top, docs/terrain.md): on flat ground the terrain at its centre, on a cell
  a face crosses the top of the face. Each against the truth, and in the navigation's frame: against the truth raised by the navigation's vertical
  error at the end of the flight, when the map was taken (quality.json per run: `map` and
  `map_nav_frame`, `nav_frame_error_end_m`). The map lives in the autopilot's frame and follows it
  (docs/terrain.md, "The navigation's frame"), as the vehicle does: the first is the map a ground
  station would compare with a survey, the second the map as the vehicle's frame had it at the
  end (the law's map where the vehicle looked last; elsewhere it carries the first pass's drift
  between places, which no map in that frame can remove).
- **obstacle height** (lap 2): the 95th percentile of the mapped heights of the footprint cells
  holding at least two points, at the end of the second lap, over the obstacle's textured height
  (the part a texture-tracking mapper can see). The table gives the least over the obstacles the
  second lap flew over (one beside the route, which the forward camera may never see, is in
  quality.json's laps, not in the table).
- **speed flown**: path length over time per lap, mean over the laps (the commanded speed beside it).

The record of a flight starts when the vehicle first reaches its commanded height after take-off
(`cruise_reached_ne_m` in quality.json): the climb-out is the autopilot's take-off, flown while
the service already commands the route (above `control.min_alt_m`). Every scenario's first
obstacle lies far enough along the first leg to be approached at the commanded height.
"""


BASELINE_FIGURES = (  # (summary key, heading, format, better: +1 higher, -1 lower)
    ("first_pass_min_clearance_fraction", "first-pass clearance", "{:.2f}", +1),
    ("cruise_excess_median_m", "cruise excess median (m)", "{:.1f}", -1),
    ("cruise_excess_p95_m", "cruise excess p95 (m)", "{:.1f}", -1),
    ("engaged_flat_fraction", "engaged over flat", "{:.2f}", -1),
    ("false_climbs", "false climbs", "{:.0f}", -1),
    ("flat_within_1m", "flat within 1 m", "{:.2f}", +1),
    ("all_rmse_m", "all RMSE (m)", "{:.2f}", -1),
    ("speed_flown_mps", "speed flown (m/s)", "{:.1f}", +1),
)


def load_baseline(path: str | os.PathLike) -> dict[str, Any]:
    """A previous run's quality.json, to compare against (ConfigError naming the file when it
    cannot be used)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except OSError as exc:
        raise ConfigError(f"--baseline {p}: cannot read: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--baseline {p}: not JSON: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA or not isinstance(doc.get("summary"), list):
        raise ConfigError(f"--baseline {p}: not a quality.json of schema {SCHEMA!r}")
    return {"path": str(p), "generated": doc.get("generated", ""), "command": doc.get("command", ""),
            "summary": doc["summary"]}


def baseline_lines(doc: dict[str, Any]) -> list[str]:
    """The per-scenario figures before (the baseline) and now, side by side: 'before -> now', with
    the change marked where it is better (+) or worse (-) by more than rounding."""
    base = doc.get("baseline")
    if not base:
        return []
    before = {(r["scenario"], r["parameterisation"]): r for r in base["summary"]}
    lines = ["## Against the baseline", "",
             f"Before: `{base['command']}` on {base['generated'][:10]} (`{base['path']}`); now: this run. "
             "Each cell is before -> now, worst over the seeds as above; (+) better, (-) worse.", "",
             "| scenario | mapper | " + " | ".join(h for _, h, _, _ in BASELINE_FIGURES) + " |",
             "|---|---|" + "---|" * len(BASELINE_FIGURES)]
    for s in doc["summary"]:
        b = before.get((s["scenario"], s["parameterisation"]))
        cells = []
        for key, _, fmt, better in BASELINE_FIGURES:
            now, old = s.get(key), (b or {}).get(key)
            mark = ""
            if isinstance(now, (int, float)) and isinstance(old, (int, float)) and fmt.format(now) != fmt.format(old):
                mark = " (+)" if (now - old) * better > 0 else " (-)"
            cells.append(f"{_f(old, fmt)} -> {_f(now, fmt)}{mark}")
        lines.append(f"| {s['scenario']} | {s['parameterisation'].replace('_', ' ')} | " + " | ".join(cells) + " |")
    return lines + [""]


def markdown(doc: dict[str, Any], figures: dict[str, str]) -> str:
    """quality.md: how it was made, the headline, the summary per scenario, the comparison with a
    baseline when one was given, every run, the pictures."""
    opts = doc["options"]
    lines = [
        "# Scenario suite: what a pilot sees",
        "",
        f"Made by `{doc['command']}` on {doc['generated'][:10]} ({doc['machine']['cpus']} cores, "
        f"Python {doc['machine']['python']}): {len(doc['runs'])} flights, {opts['laps']} laps each, "
        f"{doc['wall_s']:.0f} s wall. The flights are the service's closed loop in simulated time "
        "(companion/desk/quality/engine.py); the figures are defined below and in companion/desk/quality/metrics.py.",
        "",
    ]
    failed = [r for r in doc["runs"] if not r.get("complete")]
    if failed:
        lines += ["**Failed runs** (not dropped):", ""]
        lines += [f"- {r['scenario']} seed {r['seed']} {r['parameterisation']}: {r.get('problem') or 'laps not flown'}"
                  for r in failed]
        lines.append("")
    lines += ["## Headline", ""]
    lines += [f"- {h}" for h in headline(doc["runs"])]
    lines += ["", "## Per scenario (worst over the seeds)", "",
              "| scenario | mapper | runs ok | first-pass clearance | least clearance | warning margin (s) | "
              "cruise excess median / p95 (m) | engaged over flat | false climbs | phantom points | "
              "flat bias, nav frame / truth (m) | flat within 1 m, nav frame / truth | all RMSE, nav frame / truth (m) | "
              "obstacle height lap 2 | speed flown / commanded (m/s) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in doc["summary"]:
        lines.append(
            f"| {s['scenario']} | {s['parameterisation'].replace('_', ' ')} | {s['complete']}/{s['runs']} | "
            f"{_f(s['first_pass_min_clearance_fraction'])} | {_f(s['min_clearance_fraction'])} | "
            f"{'never held' if s.get('obstacle_never_held') else _f(s['worst_warning_margin_s'], '{:.1f}')} | "
            f"{_f(s['cruise_excess_median_m'], '{:.1f}')} / "
            f"{_f(s['cruise_excess_p95_m'], '{:.1f}')} | {_f(s['engaged_flat_fraction'])} | {s['false_climbs']} | "
            f"{_f(s.get('phantom_points'), '{:.0f}')} | {_f(s.get('flat_bias_nav_m'))} / {_f(s['flat_bias_m'])} | "
            f"{_f(s.get('flat_within_1m_nav'))} / {_f(s['flat_within_1m'])} | {_f(s.get('all_rmse_nav_m'))} / {_f(s['all_rmse_m'])} | "
            f"{_f(s['obstacle_height_lap2_fraction'])} | {_f(s['speed_flown_mps'], '{:.1f}')} / "
            f"{_f(s['speed_commanded_mps'], '{:.1f}')} |")
    lines += [""] + baseline_lines(doc)
    if doc.get("notes"):
        lines += [doc["notes"].rstrip(), ""]
    lines += ["Scenarios:", ""]
    for name, desc in sorted(doc["scenarios"].items()):
        lines.append(f"- **{name}**: {desc}")
    lines += ["", DEFINITIONS, "## Every run", "",
              "| scenario | seed | mapper | complete | clearance per lap | warning - needed per lap (s) | "
              "cruise excess median per lap (m) | engaged over flat per lap | flat bias / within 1 m | speed (m/s) | x real time |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["runs"]:
        laps = r.get("laps") or []
        lines.append(
            f"| {r['scenario']} | {r['seed']} | {r['parameterisation'].replace('_', ' ')} | {'yes' if r.get('complete') else 'NO'} | "
            + " ".join(_f(lap.get("min_clearance_fraction")) for lap in laps) + " | "
            + " ".join("never" if lap.get("warning_s") is None and lap.get("needed_s") is not None else
                       _f(None if lap.get("warning_s") is None else lap["warning_s"] - lap["needed_s"], "{:.1f}")
                       for lap in laps) + " | "
            + " ".join(_f(lap.get("cruise_excess_median_m"), "{:.1f}") for lap in laps) + " | "
            + " ".join(_f(lap.get("engaged_flat_fraction")) for lap in laps) + " | "
            + f"{_f(r['map']['flat'].get('bias_m'))} / {_f(r['map']['flat'].get('within_1m'))} | "
            + f"{_f(r.get('speed_flown_mps'), '{:.1f}')} | {_f(r.get('realtime_factor'), '{:.0f}')} |")
    if figures:
        lines += ["", "## Worst first pass of each scenario", ""]
        for name, rel in sorted(figures.items()):
            lines += [f"![{name}: worst first pass]({rel})", ""]
    return "\n".join(lines) + "\n"


def headline(runs: list[dict]) -> list[str]:
    """The worst first-pass clearance and the worst cruise excess, each with where it happened."""
    out = []
    for param in PARAMETERISATIONS:
        group = [r for r in runs if r["parameterisation"] == param and r.get("laps")]
        firsts = [(r["laps"][0].get("min_clearance_fraction"), r) for r in group
                  if r["laps"][0].get("min_clearance_fraction") is not None]
        excess = [(lap.get("cruise_excess_median_m"), lap.get("cruise_excess_p95_m"), lap["lap"], r)
                  for r in group for lap in r["laps"] if lap.get("cruise_excess_median_m") is not None]
        name = param.replace("_", " ")
        if firsts:
            v, r = min(firsts, key=lambda x: x[0])
            out.append(f"{name}: worst first-pass clearance {v:.2f} of the configured clearance "
                       f"({r['scenario']}, seed {r['seed']}, over {r['laps'][0].get('warning_obstacle') or 'flat ground'})")
        if excess:
            m, p, lap, r = max(excess, key=lambda x: x[0])
            out.append(f"{name}: worst cruise excess {m:.1f} m median, {_f(p, '{:.1f}')} m p95 "
                       f"({r['scenario']}, seed {r['seed']}, lap {lap})")
    return out


def worst_first_pass_figures(results: list[dict], folder: Path, rel_prefix: str) -> dict[str, str]:
    """One side profile per scenario: its run with the least first-lap clearance fraction."""
    from companion.desk.quality.figures import side_profile

    out = {}
    by_scenario: dict[str, list[dict]] = {}
    for res in results:
        if res["profile"] is not None and res["run"].get("laps"):
            by_scenario.setdefault(res["run"]["scenario"], []).append(res)
    for scenario, group in by_scenario.items():
        res = min(group, key=lambda x: x["run"]["laps"][0].get("min_clearance_fraction") or math.inf)
        run, prof = res["run"], res["profile"]
        lap = run["laps"][0]
        name = f"{scenario}_worst_first_pass.png"
        title = (f"{scenario}: worst first pass ({run['parameterisation'].replace('_', ' ')}, seed {run['seed']}): "
                 f"least clearance {_f(lap.get('min_clearance_fraction'))} of {run['clearance_m']:g} m")
        side_profile(folder / name, *(np.asarray(prof[k], float) for k in
                                      ("distance_m", "alt_m", "true_terrain_m", "mapped_terrain_m", "mapped_corridor_max_m")),
                     clearance_m=float(run["clearance_m"]), nominal_alt_m=float(run["nominal_alt_m"]), title=title)
        out[scenario] = f"{rel_prefix}{name}"
    return out


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", action="append", metavar="NAME",
                   help="scenario name in config/scenarios/ or a YAML path (repeatable; default: every scenario)")
    p.add_argument("--seeds", default="3", help="a count (3 = seeds 1..3) or a list (1,5,9); default 3")
    p.add_argument("--parameterisation", choices=("inverse_depth", "cartesian", "both"), default="both")
    p.add_argument("--laps", type=int, default=DEFAULT_LAPS, help=f"laps per flight (default {DEFAULT_LAPS})")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="flights in parallel (default: the cores)")
    p.add_argument("--quick", action="store_true",
                   help=f"a CI-sized subset: scenarios {', '.join(QUICK_SCENARIOS)}, seed 1, inverse depth, 1 lap")
    p.add_argument("--config", metavar="FILE", help="service configuration applied to every flight (YAML, partial)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="one service setting for every flight (repeatable; after --config)")
    p.add_argument("--baseline", metavar="QUALITY_JSON",
                   help="a previous run's quality.json: quality.md then shows each scenario's figures before and now")
    p.add_argument("--notes", metavar="MARKDOWN",
                   help="a Markdown file put into quality.md after the tables (what the figures mean, written by a person; read when the flights are done)")
    p.add_argument("--output", default="quality-report",
                   help="folder for quality.json, quality.md and quality/*.png (docs = the committed table)")
    p.add_argument("--shared-first-pass", type=int, metavar="SCOUT_LAPS",
                   help="instead of the suite: per scenario and seed, a scout flies SCOUT_LAPS laps, then the first lap "
                        "is flown alone and with the scout's map (inverse depth); writes shared.md and shared.json")


def _mmss(seconds: float) -> str:
    return f"{int(seconds // 60)}m{int(seconds % 60):02d}s"


class Progress:
    """``[#####-----] 12/54 flights, 0 failed, 3m10s, ~9m left`` on stderr (in place on a terminal)."""

    def __init__(self, total: int, stream=None):
        self.total, self.stream = total, stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = time.monotonic()

    def show(self, done: int, failed: int, last: str = "") -> None:
        el = time.monotonic() - self.t0
        left = el / done * (self.total - done) if done else math.nan
        bar = "#" * int(round(20 * done / max(1, self.total)))
        text = (f"[{bar:<20}] {done}/{self.total} flights, {failed} failed, {_mmss(el)}"
                + (f", ~{_mmss(left)} left" if math.isfinite(left) else "")
                + (f"  {last}" if last else ""))
        self.stream.write(("\r" + text.ljust(110)) if self.tty else text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def main(args: argparse.Namespace) -> int:
    from companion.desk.quality.scenarios import flight_config
    from drivers.sim.world import World

    try:
        if args.quick:
            scenarios, seeds, params, laps = list(QUICK_SCENARIOS), [1], ["inverse_depth"], 1
        else:
            scenarios = args.scenario or scenario_names()
            seeds = parse_seeds(args.seeds)
            params = list(PARAMETERISATIONS) if args.parameterisation == "both" else [args.parameterisation]
            laps = args.laps
        if not 1 <= laps <= 50:
            raise ConfigError(f"--laps must be within 1..50, got {laps}")
        if not 1 <= args.jobs <= 256:
            raise ConfigError(f"--jobs must be within 1..256, got {args.jobs}")
        overrides = _overrides(args)
        baseline = load_baseline(args.baseline) if args.baseline else None
        if args.notes and not Path(args.notes).is_file():
            raise ConfigError(f"--notes {args.notes}: no such file")
        # Every scenario and override is validated before any flight starts.
        for s in scenarios:
            flight_config(World.load(s), s, params[0], seeds[0], CAMERA_RATE_HZ, overrides)
        if args.shared_first_pass is not None and not 1 <= args.shared_first_pass <= 20:
            raise ConfigError(f"--shared-first-pass must be within 1..20 laps, got {args.shared_first_pass}")
    except ConfigError as exc:
        print(f"companion quality: {exc}", file=sys.stderr)
        return 2
    if args.shared_first_pass is not None:
        from companion.desk.quality import fleet

        command = "companion quality " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else "companion quality"
        return fleet.run(scenarios, seeds, args.shared_first_pass, overrides, args.jobs, Path(args.output), command)
    jobs = [(s, seed, p, laps, overrides) for s in scenarios for p in params for seed in seeds]
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    print(f"companion quality: {len(scenarios)} scenario(s) x {len(seeds)} seed(s) x {len(params)} mapper(s) = "
          f"{len(jobs)} flights of {laps} lap(s), {min(args.jobs, len(jobs))} at a time; report in {out}/", file=sys.stderr)
    progress = Progress(len(jobs))
    results, failed = [], 0
    t0 = time.monotonic()
    progress.show(0, 0)
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(processes=max(1, min(args.jobs, len(jobs))), maxtasksperchild=4) as pool:
        for res in pool.imap_unordered(fly_one, jobs):
            results.append(res)
            r = res["run"]
            failed += 0 if r.get("complete") else 1
            progress.show(len(results), failed, f"{r['scenario']} s{r['seed']} {r['parameterisation']}")
    progress.close()
    order = {j[:3]: i for i, j in enumerate(jobs)}
    results.sort(key=lambda x: order.get((x["run"]["scenario"], x["run"]["seed"], x["run"]["parameterisation"]), 0))
    runs = [res["run"] for res in results]
    wall = time.monotonic() - t0
    command = "companion quality " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else "companion quality"
    doc = {
        "schema": SCHEMA,
        "generated": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": command,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "options": {"scenarios": scenarios, "seeds": seeds, "parameterisations": params, "laps": laps,
                    "overrides": [src for src, _ in overrides], "camera_rate_hz": CAMERA_RATE_HZ},
        "wall_s": round(wall, 1),
        "scenarios": {res["run"]["scenario"]: res["description"] for res in results if res["description"]},
        "summary": summarise(runs),
        "runs": runs,
    }
    if baseline is not None:
        doc["baseline"] = baseline
    if args.notes:  # read after the flights, so that it can be written while they fly
        try:
            doc["notes"] = Path(args.notes).read_text()
        except OSError as exc:
            print(f"companion quality: --notes {args.notes}: cannot read: {exc.strerror or exc}; written without it",
                  file=sys.stderr)
    fig_dir = out / "quality"
    try:
        figures = worst_first_pass_figures(results, fig_dir, "quality/")
    except RuntimeError as exc:  # matplotlib (the desk extra) missing: the tables still stand
        print(f"companion quality: no pictures: {exc}", file=sys.stderr)
        figures = {}
    (out / "quality.json").write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    (out / "quality.md").write_text(markdown(doc, figures))
    for line in headline(runs):
        print(f"companion quality: {line}", file=sys.stderr)
    print(f"companion quality: {len(runs) - failed} of {len(runs)} flights complete in {wall:.0f} s; "
          f"wrote {out / 'quality.md'} and {out / 'quality.json'}", file=sys.stderr)
    return 0 if failed == 0 else 1
