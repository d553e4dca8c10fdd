"""Shared pieces of the benchmarks: one-core pinning, machine description, statistics, and the
rendered flight that every mapper figure is measured on.

The flight: the default scenario's first leg (north along east = 0, over the 12 m building at
north 100), 6 m/s, camera frames at ``RATE_HZ``, 15 m above the ground with the climb over the
building that the avoidance law would fly (15 m above the roof). Images are rendered by
``drivers.sim.renderer.Renderer`` at the *true* pose; the navigation state handed to the mapper is
the truth plus an error drawn from the covariance it is told (``SIGMA_POS_M``, ``SIGMA_ATT_RAD``),
so the mapper tracks real Harris corners of a textured world.
"""

from __future__ import annotations

import math
import os
import platform
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from companion.config import CompanionConfig, MapperConfig, replace
from companion.method.geometry import CameraMount, PinholeCamera, camera_from_config, euler_to_matrix, matrix_to_quat, so3_exp
from companion.method.messages import NavState

RATE_HZ = 30.0
SPEED_MPS = 6.0
START_NORTH_M = 10.0
ALT_AGL_M = 15.0
ROOF_M = 12.0
SIGMA_POS_M = 0.05
SIGMA_ATT_RAD = math.radians(0.2)


# ------------------------------------------------------------------------------------------------
# Machine and pinning
# ------------------------------------------------------------------------------------------------


def pin_one_core(core: int = 0) -> bool:
    """Run this process on one core with OpenCV single-threaded (the single-core figures)."""
    cv2.setNumThreads(1)
    try:
        os.sched_setaffinity(0, {core})
        return True
    except (AttributeError, OSError):
        return False


def unpin() -> None:
    try:
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
    except (AttributeError, OSError):
        pass


def cpu_model() -> str:
    """Model name, family and model of the first CPU (Linux), else what ``platform`` knows."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break
                key, _, value = line.partition(":")
                fields[key.strip()] = value.strip()
    except OSError:
        pass
    name = fields.get("model name") or platform.processor() or platform.machine()
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def machine_info() -> dict:
    try:
        load = os.getloadavg()
    except OSError:
        load = (math.nan,) * 3
    try:
        affinity = sorted(os.sched_getaffinity(0))
    except AttributeError:
        affinity = []
    return {
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "affinity": affinity,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "platform": platform.platform(),
        "loadavg": [round(x, 2) for x in load],
    }


# ------------------------------------------------------------------------------------------------
# Statistics
# ------------------------------------------------------------------------------------------------


def summary(samples_ms) -> dict:
    """median, p99, mean, min, n of a list of times (ms)."""
    a = np.asarray(samples_ms, float)
    if a.size == 0:
        return {"n": 0, "median": None, "p99": None, "mean": None, "min": None}
    return {"n": int(a.size), "median": float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "mean": float(a.mean()), "min": float(a.min())}


def time_calls(fn: Callable[[], object], repeats: int, warmup: int = 3) -> list[float]:
    """Wall time (ms) of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def fmt(x, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if isinstance(x, int):
        return str(x)
    if abs(x) >= 100:
        return f"{x:.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    return f"{x:.{digits}f}" if abs(x) < 1 else f"{x:.2f}"


def table(headers: list[str], rows: list[list]) -> str:
    cells = [[h for h in headers]] + [[r if isinstance(r, str) else fmt(r) for r in row] for row in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(headers))]
    lines = ["  ".join(c.rjust(w) if j else c.ljust(w) for j, (c, w) in enumerate(zip(row, widths))) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
# Configuration of the mapper for N features
# ------------------------------------------------------------------------------------------------


def base_config() -> CompanionConfig:
    return CompanionConfig()


def mapper_config(n_features: int, base: MapperConfig | None = None) -> MapperConfig:
    """The mapper with a database of ``n_features`` (the paper's 50 by default).

    The detector passes on twice as many corners as the database holds (the default ratio,
    100 for 50); the per-bin cap grows with that so the 8 x 6 bins can deliver them (at least 4,
    the default, and 1.5 times the even share)."""
    base = base or MapperConfig()
    n_det = 2 * n_features
    per_bin = max(base.per_bin, int(math.ceil(1.5 * n_det / (base.bins_x * base.bins_y))))
    return replace(base, max_features=n_features, max_detections=n_det, per_bin=per_bin)


# ------------------------------------------------------------------------------------------------
# The rendered flight
# ------------------------------------------------------------------------------------------------


def smoothstep(x: np.ndarray | float, a: float, b: float):
    s = np.clip((np.asarray(x, float) - a) / (b - a), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def altitude_profile(north: float) -> float:
    """15 m above the ground, climbing to 15 m above the 12 m roof over north 60..85 and back down
    after it (north 115..140), as the pull-up law would fly it."""
    up = smoothstep(north, 60.0, 85.0) - smoothstep(north, 115.0, 140.0)
    return ALT_AGL_M + ROOF_M * float(up)


def body_pose(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True body position (3,), R_nb (3, 3) and velocity (3,) at flight time ``t`` (s)."""
    north = START_NORTH_M + SPEED_MPS * t
    alt = altitude_profile(north)
    p = np.array([north, 0.3 * math.sin(0.7 * t), -alt + 0.2 * math.sin(0.5 * t)])
    R = euler_to_matrix(math.radians(2.0) * math.sin(1.3 * t), math.radians(1.5) * math.sin(0.9 * t),
                        math.radians(1.0) * math.sin(0.4 * t))
    dt = 1e-3
    alt2 = altitude_profile(north + SPEED_MPS * dt)
    v = np.array([SPEED_MPS, 0.21 * math.cos(0.7 * t), -(alt2 - alt) / dt + 0.1 * math.cos(0.5 * t)])
    return p, R, v


def nav_covariance() -> np.ndarray:
    cov = np.zeros((9, 9))
    cov[0:3, 0:3] = np.eye(3) * SIGMA_POS_M**2
    cov[3:6, 3:6] = np.eye(3) * 0.1**2
    cov[6:9, 6:9] = np.eye(3) * SIGMA_ATT_RAD**2
    return cov


@dataclass(frozen=True)
class Flight:
    """Rendered frames and navigation: images (N,) of (H, W) uint8; navs (N,) NavState (truth plus
    noise drawn from its covariance); p_c (N, 3) true camera centres."""

    images: tuple[np.ndarray, ...]
    navs: tuple[NavState, ...]
    p_c: np.ndarray
    camera: PinholeCamera
    mount: CameraMount
    cfg: CompanionConfig
    render_ms: tuple[float, ...]

    def __len__(self) -> int:
        return len(self.images)


def render_flight(n_frames: int, cfg: CompanionConfig | None = None, seed: int = 7, rate_hz: float = RATE_HZ) -> Flight:
    """``n_frames`` consecutive frames at ``rate_hz`` along the flight described in the module docstring."""
    from drivers.sim.renderer import Renderer, RenderOptions
    from drivers.sim.world import World

    cfg = cfg or base_config()
    camera, mount = camera_from_config(cfg.camera)
    world = World.load(cfg.sim.scenario)
    renderer = Renderer(world, camera, RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, seed=seed))
    rng = np.random.default_rng(seed)
    cov = nav_covariance()
    images, navs, centres, render_ms = [], [], [], []
    for k in range(n_frames):
        t = k / rate_hz
        p, R_nb, v = body_pose(t)
        p_c, R_nc = mount.camera_pose(p, R_nb)
        t0 = time.perf_counter()
        images.append(renderer.render(p_c, R_nc))
        render_ms.append((time.perf_counter() - t0) * 1e3)
        p_est = p + rng.normal(0.0, SIGMA_POS_M, 3)
        R_est = so3_exp(-rng.normal(0.0, SIGMA_ATT_RAD, 3)) @ R_nb
        navs.append(NavState(t, p_est, v, matrix_to_quat(R_est), cov))
        centres.append(p_c)
    return Flight(tuple(images), tuple(navs), np.array(centres), camera, mount, cfg, tuple(render_ms))
