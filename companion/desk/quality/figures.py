"""Figures of the scenario suite, drawn with matplotlib (the ``desk`` extra: the vehicle never needs it).

:func:`side_profile` draws one lap along the path flown: the vehicle's true altitude, the true
terrain below it, the mapped terrain under the path and the highest mapped cell the law looks at
across the corridor, and the terrain plus the configured clearance (the line the altitude should
stay above).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    try:
        import matplotlib
    except ModuleNotFoundError as exc:  # the desk extra is not installed
        raise RuntimeError("figures need matplotlib: pip install 'companion[desk]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def side_profile(path: Path, distance_m: np.ndarray, alt_m: np.ndarray, true_terrain_m: np.ndarray,
                 mapped_m: np.ndarray, corridor_max_m: np.ndarray, clearance_m: float, nominal_alt_m: float,
                 title: str) -> Path:
    """One side profile as a PNG (all arrays (M,) along the path; NaN = unknown map)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(10, 4.2), dpi=110, layout="constrained")
    ax.fill_between(distance_m, 0.0, true_terrain_m, color="#b5a48b", alpha=0.8, label="true terrain", step=None)
    ax.plot(distance_m, true_terrain_m + clearance_m, "--", color="#c0392b", lw=1.0,
            label=f"true terrain + clearance {clearance_m:g} m")
    ax.axhline(nominal_alt_m, color="#7f8c8d", lw=0.8, ls=":", label=f"commanded height {nominal_alt_m:g} m")
    ax.plot(distance_m, corridor_max_m, color="#e67e22", lw=0.8, alpha=0.9, label="mapped: highest cell across the corridor")
    ax.plot(distance_m, mapped_m, ".", color="#27ae60", ms=2.0, label="mapped terrain under the path")
    ax.plot(distance_m, alt_m, color="#1f4e9c", lw=1.8, label="altitude (truth)")
    ax.set_xlabel("distance along the lap (m)")
    ax.set_ylabel("altitude (m)")
    ax.set_title(title, fontsize=10)
    top = np.nanmax(np.concatenate([alt_m, true_terrain_m + clearance_m])) if len(alt_m) else 1.0
    ax.set_ylim(min(0.0, float(np.nanmin(true_terrain_m)) if len(true_terrain_m) else 0.0) - 1.0, top * 1.15 + 1.0)
    ax.set_xlim(0.0, float(distance_m[-1]) if len(distance_m) else 1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=7.5, ncol=3, framealpha=0.85)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
