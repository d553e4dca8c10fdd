"""The demo's PNGs: per run the map with the laps flown and a side profile per lap, and the comparison
of the parameterisations (mapped height and least clearance per lap)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from companion.desk import plots, report
from companion.desk.demo.flight import RunRecord

CLEARANCE_ISSUE, CLEARANCE_GOAL = 0.8, 0.9
MAP_MARGIN_M = 40.0            # the map figure shows the circuit and this much around it
MAP_RANGE_M = (-5.0, 2.0)      # colour range: from -5 m to twice the obstacle's roof height


def write_figures(records: dict[str, RunRecord], world, obstacle, out: Path) -> list[Path]:
    """map_<p>.png, profile_<p>_lap<k>.png for each run, and comparison.png."""
    written = []
    from companion.config import AvoidanceConfig

    outlines = [o.footprint_ne_m for o in world.obstacles]
    clearance = float(world.clearance_m)
    miss = AvoidanceConfig().miss_distance_m  # the law's corridor half-width (the demo keeps the default)
    for param, rec in records.items():
        t, ne, alt = rec.truth.arrays()
        starts = [0] + rec.lap_ends[:-1]
        paths = [(ne[s:e + 1], f"lap {k + 1}", plots.PALETTE[k % len(plots.PALETTE)])
                 for k, (s, e) in enumerate(zip(starts, rec.lap_ends))]
        m = rec.final_map
        if m.shape[0] and m.shape[1]:
            wp = np.asarray(world.waypoints_ne_m, float)
            lo, hi = wp.min(axis=0) - MAP_MARGIN_M, wp.max(axis=0) + MAP_MARGIN_M
            view = m.crop(lo[0], hi[0], lo[1], hi[1])
            outside = m.observed_cells() - view.observed_cells()
            vmin, vmax = MAP_RANGE_M[0], MAP_RANGE_M[1] * obstacle.height_m
            written.append(plots.height_map(
                out / f"map_{param}.png", view.height, view.north0_m, view.east0_m, view.cell_m,
                f"{param.replace('_', ' ')}: terrain map (altitude, m) after {len(rec.lap_ends)} lap(s)",
                paths=paths, outlines=outlines, vmin=vmin, vmax=vmax, scale_px=max(1, min(4, 840 // view.shape[0])),
                notes=[f"outlines: true footprints ({obstacle.name}: roof {obstacle.height_m:g} m, "
                       f"textured to {obstacle.textured_height_m:g} m)",
                       f"colours clipped to {vmin:g}..{vmax:g} m; view: circuit + {MAP_MARGIN_M:g} m "
                       f"({outside} mapped cells lie outside it)"]))
        for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
            prof = report.lap_profile(ne[s:e + 1], alt[s:e + 1], world.terrain_height, rec.lap_maps[k],
                                      lambda n, e_: world.terrain_height(n, e_, textured_only=True), corridor_m=miss)
            d = prof.distance_m
            series = [
                plots.Series(d, prof.true_terrain_m, "true terrain", plots.PALETTE[5], 1, fill_to_bottom=True),
                plots.Series(d, prof.mapped_corridor_max_m, f"mapped, highest within {miss:g} m across",
                             plots.PALETTE[3], 1),
                plots.Series(d, prof.mapped_terrain_m, "mapped terrain under the path", plots.PALETTE[2], 2),
                plots.Series(d, prof.true_terrain_m + clearance, f"terrain + clearance {clearance:g} m",
                             plots.PALETTE[1], 1, dashed=True),
                plots.Series(d, prof.alt_m, "altitude (truth)", plots.PALETTE[0], 2),
            ]
            written.append(plots.line_chart(
                out / f"profile_{param}_lap{k + 1}.png", series,
                f"{param.replace('_', ' ')}, lap {k + 1}: side profile along the circuit",
                "distance along the lap (m); mapped = the ground station's map at the lap's end", "altitude (m)"))
    written.append(comparison_figure(records, world, obstacle, out / "comparison.png"))
    return written


def comparison_figure(records: dict[str, RunRecord], world, obstacle, path: Path) -> Path:
    """Two bar charts stacked: mapped obstacle height per lap (textured height as reference), and
    the least clearance over the obstacle per lap (configured clearance as reference)."""
    import cv2

    n_laps = max((len(r.lap_ends) for r in records.values()), default=0)
    ground = report.ground_around(obstacle.footprint_ne_m, world.terrain_height)
    groups = [f"lap {k + 1}" for k in range(max(1, n_laps))]
    heights, clearances = {}, {}
    for param, rec in records.items():
        t, ne, alt = rec.truth.arrays()
        starts = [0] + rec.lap_ends[:-1]
        h, c = [], []
        for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
            h.append(report.mapped_height_over_footprint(rec.lap_maps[k], obstacle.footprint_ne_m, ground_m=ground).height_m)
            c.append(report.min_clearance_over_footprint(t[s:e + 1], ne[s:e + 1], alt[s:e + 1], obstacle.footprint_ne_m,
                                                         world.terrain_height).min_clearance_m)
        heights[param.replace("_", " ")] = h
        clearances[param.replace("_", " ")] = c
    tmp = path.with_name(path.stem + ".parts")
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        a = plots.bar_chart(tmp / "h.png", groups, heights,
                            f"{obstacle.name}: mapped height at the end of each lap (m)", "height (m)",
                            reference=[(obstacle.textured_height_m, f"textured height {obstacle.textured_height_m:g} m"),
                                       (obstacle.height_m, f"roof {obstacle.height_m:g} m", plots.GREY),
                                       (report.PAPER_MAPPED_FRACTION * obstacle.height_m,
                                        f"paper: {100 * report.PAPER_MAPPED_FRACTION:.0f}% of the roof", plots.PALETTE[3])],
                            size=(760, 400))
        b = plots.bar_chart(tmp / "c.png", groups, clearances,
                            f"{obstacle.name}: least clearance over it in each lap (m)", "clearance (m)",
                            reference=[(float(world.clearance_m), f"configured {world.clearance_m:g} m"),
                                       (CLEARANCE_ISSUE * world.clearance_m, f"issue: {CLEARANCE_ISSUE:g} x configured", plots.GREY),
                                       (CLEARANCE_GOAL * world.clearance_m, f"goal: {CLEARANCE_GOAL:g} x configured",
                                        plots.PALETTE[3])],
                            size=(760, 400))
        parts = [cv2.imread(str(a)), cv2.imread(str(b))]
        width = max(part.shape[1] for part in parts)  # tight bounding boxes differ by their legends
        img = np.vstack([cv2.copyMakeBorder(part, 0, 0, 0, width - part.shape[1], cv2.BORDER_CONSTANT,
                                            value=plots.WHITE) for part in parts])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return plots.write_png(path, img)
