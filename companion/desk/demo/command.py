"""``companion demo``: the options, a closed-loop run per parameterisation, and the report folder
(``metrics.json``, the PNGs, each run saved for ``--replot``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from companion.config import ConfigError
from companion.desk import plots
from companion.desk.demo.figures import write_figures
from companion.desk.demo.flight import RunRecord, run_closed_loop
from companion.desk.demo.progress import Progress
from companion.desk.demo.results import build_metrics, load_record, save_record, summary_lines, write_trajectory

PARAMETERISATIONS = ("inverse_depth", "cartesian")
DEFAULT_SPEEDUP = 3.0          # both runs of 3 laps in about 3.5 min on the 2-core machine, frames kept up (docs/demo.md)
CAMERA_RATE_HZ = 15.0          # simulated seconds; the paper's camera ran at 16 Hz


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="default", help="scenario name in config/scenarios/ or a YAML path (default: default)")
    p.add_argument("--laps", type=int, default=3, help="laps of the circuit per run (default 3, as in the paper)")
    p.add_argument("--speedup", type=float, default=DEFAULT_SPEEDUP,
                   help=f"simulated seconds per wall second for the vehicle and the service (default {DEFAULT_SPEEDUP:g})")
    p.add_argument("--no-lockstep", action="store_true",
                   help="pace the flight by the wall clock alone: frames the service cannot map in time are dropped "
                        "(default: the service holds the simulation's clock while its mapper is behind, docs/sim.md)")
    p.add_argument("--output", default="demo-report", help="report folder (default ./demo-report)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulated navigation error, wind and camera noise")
    p.add_argument("--no-avoid", action="store_true",
                   help="hold the nominal altitude only (the law is still evaluated and published, not obeyed)")
    p.add_argument("--parameterisation", choices=("inverse_depth", "cartesian", "both"), default="both",
                   help="mapper feature parameterisation; both = inverse depth, then the Cartesian baseline (default)")
    p.add_argument("--replot", action="store_true",
                   help="do not fly: rebuild metrics.json and the figures from the runs saved in --output")
    p.add_argument("--config", metavar="FILE",
                   help="service configuration for the run (YAML, partial; over the scenario's own settings)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="one service setting for the run, e.g. camera.mount_pitch_deg=-30 (repeatable; after --config)")
    p.add_argument("--camera-rate", type=float, default=CAMERA_RATE_HZ, metavar="HZ",
                   help=f"synthetic camera rate in simulated Hz (default {CAMERA_RATE_HZ:g})")
    p.add_argument("--http", metavar="HOST:PORT",
                   help="watch the flight live in a browser: the demo's ground station serves its map page here "
                        "(as companion ground --http does), e.g. 127.0.0.1:8080")


def _check_options(args: argparse.Namespace) -> None:
    if not 1 <= args.laps <= 100:
        raise ConfigError(f"--laps must be within 1..100, got {args.laps}")
    if not (math.isfinite(args.speedup) and 0.1 <= args.speedup <= 100.0):
        raise ConfigError(f"--speedup must be within 0.1..100, got {args.speedup}")
    if not (math.isfinite(args.camera_rate) and 0.5 <= args.camera_rate <= 60.0):
        raise ConfigError(f"--camera-rate must be within 0.5..60 Hz, got {args.camera_rate}")
    if not 0 <= args.seed < 2**31:
        raise ConfigError(f"--seed must be within 0..2^31-1, got {args.seed}")
    if getattr(args, "http", None):
        from drivers.ground_web import parse_address

        try:
            parse_address(args.http)
        except ValueError as exc:
            raise ConfigError(f"--http {exc}") from None


def main(args: argparse.Namespace) -> int:
    from drivers.sim.world import World

    from companion.desk.quality.scenarios import flight_config, override_layers, world_for

    try:
        _check_options(args)
        world = World.load(args.scenario)
        # --config / --set are validated like `companion run`'s configuration before anything starts;
        # the figures are then judged against the circuit the service was told to fly
        args.overrides = override_layers(getattr(args, "config", None), getattr(args, "set", None))
        world = world_for(world, flight_config(world, args.scenario, "inverse_depth", args.seed, args.camera_rate,
                                               args.overrides))
        plots.require()  # before the flight, not at its figures
    except (ConfigError, plots.DeskExtraMissing) as exc:
        print(f"companion demo: {exc}", file=sys.stderr)
        return 2
    obstacle = pick_obstacle(world)
    if obstacle is None:
        print(f"companion demo: scenario {args.scenario!r} has no obstacle to fly over", file=sys.stderr)
        return 2
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    params = PARAMETERISATIONS if args.parameterisation == "both" else (args.parameterisation,)
    progress = Progress()
    progress.say(f"companion demo: scenario {args.scenario}, {args.laps} lap(s), x{args.speedup:g} real time, "
                 f"{' then '.join(params)}{', avoidance OFF' if args.no_avoid else ''}; report in {out}/")
    wall0 = time.monotonic()
    records: dict[str, RunRecord] = {}
    interrupted = False
    if args.replot:
        for p in params:
            path = out / "runs" / p / "record.npz"
            if not path.exists():
                print(f"companion demo: --replot: no saved run {path}", file=sys.stderr)
                return 2
            records[p] = load_record(path)
            for k, v in (records[p].options or {}).items():
                setattr(args, k, v)  # the figures describe the run as it was flown
        args.overrides = override_layers(args.config, args.set)
        world = world_for(World.load(args.scenario), flight_config(World.load(args.scenario), args.scenario, "inverse_depth",
                                                                   args.seed, args.camera_rate, args.overrides))
    else:
        try:
            for p in params:
                records[p] = run_closed_loop(p, args, world, obstacle, out / "runs" / p, progress)
                if records[p].problem:
                    progress.say(f"companion demo: {p}: {records[p].problem}")
                save_record(records[p], out / "runs" / p / "record.npz", args)
                write_trajectory(records[p], out / "runs" / p / "trajectory.csv")
        except KeyboardInterrupt:
            interrupted = True
            progress.say("companion demo: interrupted; writing what was flown")
    wall = time.monotonic() - wall0 if not args.replot else sum(r.wall_s for r in records.values())
    metrics = build_metrics(records, world, obstacle, args, wall)
    figures = write_figures({p: r for p, r in records.items() if r.lap_ends}, world, obstacle, out)
    metrics["figures"] = [f.name for f in figures]
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=2, allow_nan=False))
    os.replace(tmp, out / "metrics.json")
    for line in summary_lines(metrics):
        progress.say(line)
    progress.say(f"companion demo: {wall:.0f} s wall; wrote {out / 'metrics.json'} and {len(figures)} PNG(s)")
    ok = not interrupted and all(r.complete for r in records.values())
    return 0 if ok else 1


def pick_obstacle(world):
    """The structure the report is about: the tallest building, else the tallest obstacle."""
    if not world.obstacles:
        return None
    buildings = [o for o in world.obstacles if o.kind == "building"] or list(world.obstacles)
    return max(buildings, key=lambda o: o.height_m)
